"""The measurements inside the windows of distance rejections are left out of the GP fits
(rtsgt.filtering.gates, section on the windows; rtsgt.pipeline).

Closed forms for the windows, then simulated deployments with known truth in which one station
tracks another prism of the robot for 14 s: the distance gate rejects those poses, and the
GPs fitted without the window get the Qc and the pose sigmas of the same deployment with the
window cut from the input, while the old behaviour (``outlier_windows = "keep"``) does not.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rtsgt.filtering.gates import (
    distance_outliers,
    in_windows,
    outlier_windows,
    prism_distances,
)
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import read_run, write_run
from rtsgt.measurement.polar import cartesian_to_polar
from rtsgt.pipeline import run_pipeline
from rtsgt.pose import ReferencePoints, estimate_poses
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth
from rtsgt.simulation.deployment import WARTHOG_PRISMS_ROBOT_M

#: A fourth prism on the robot, tracked by no station: the one station 2 locks on.
SPARE_PRISM_ROBOT_M = WARTHOG_PRISMS_ROBOT_M[3]
WINDOW_S = 14.0
#: Tolerances of the fit without the window against the cut input (which leaves out a few
#: measurements more or less at the window's edges): Qc of the horizontal axes and the median
#: pose sigma. The vertical Qc, a thousand times smaller and weakly determined by
#: leave-one-out (a flat optimum), moves by up to about 12 % with those few measurements.
QC_RTOL = 0.15
QC_VERTICAL_RTOL = 0.25
SIGMA_RTOL = 0.10


# --- closed forms ---------------------------------------------------------------------------

def test_windows_are_padded_up_to_the_neighbouring_queries_and_merged():
    t = np.concatenate([np.arange(0.0, 2.01, 0.2), [5.0, 5.2]])  # a gap after 2.0 s
    flag = np.zeros(t.size, bool)
    flag[[3, 4, 5]] = True  # 0.6-1.0 s: one window padded by 0.2 s
    flag[10] = True  # 2.0 s: the next query is 3 s away, padded by one step (0.2 s)
    flag[11] = True  # 5.0 s: the first after the gap, padded by one step before
    w = outlier_windows(t, flag)
    np.testing.assert_allclose(w, [[0.4, 1.2], [1.8, 2.2], [4.8, 5.2]], atol=1e-12)
    # an isolated first pose is padded by one step before it; adjacent windows merge
    flag = np.zeros(t.size, bool)
    flag[[0, 1]] = True
    np.testing.assert_allclose(outlier_windows(t, flag), [[-0.2, 0.4]], atol=1e-12)
    np.testing.assert_allclose(outlier_windows(t, flag, step=0.1), [[-0.1, 0.3]], atol=1e-12)
    assert outlier_windows(t, np.zeros(t.size, bool)).shape == (0, 2)
    with pytest.raises(ValueError):
        outlier_windows(t[::-1], flag)


def test_in_windows_is_open():
    w = np.array([[0.4, 1.2], [1.8, 2.2]])
    t = np.array([0.4, 0.41, 1.19, 1.2, 1.5, 1.81, 2.3, -1.0])
    np.testing.assert_array_equal(in_windows(t, w),
                                  [False, True, True, False, False, True, False, False])
    assert not in_windows(t, np.zeros((0, 2))).any()


def test_distance_outliers_count_collinear_poses_not_missing_prisms():
    r = np.array([[0.4, 0.3, 0.8], [0.4, -0.42, 0.64], [-0.45, 0.05, 0.95]])
    ref = ReferencePoints(("1", "2", "3"), r, np.eye(9) * 1e-8)
    q = np.repeat(r[None], 4, axis=0) + np.array([10.0, 5.0, 0.0])
    u = (r[1] - r[0]) / np.linalg.norm(r[1] - r[0])
    q[1, 1] += 0.08 * u  # prisms 1-2 8 cm further apart (2-3 at most 8 cm): inside the gate
    q[2, 1] = q[2, 2] + [0.001, 0.0, 0.0]  # prism 2 on prism 3: collinear, and wrong
    q[3, 0] = np.nan  # a prism missing: nothing to say
    cov = np.repeat(np.eye(3)[None, None] * 1e-6, 4, axis=0).repeat(3, axis=1)
    est = estimate_poses(q, cov, ref, engine="linear")
    assert est.reason[2] == "collinear" and est.reason[3] == "missing_prism"
    np.testing.assert_array_equal(distance_outliers(est, ref, 0.10), [False, False, True, False])
    np.testing.assert_array_equal(distance_outliers(est, ref, 0.05), [False, True, True, False])
    # the same flags from the prisms alone, no pose estimated (the refits flag by them)
    d = prism_distances(q)
    assert d.pairs == est.pairs
    np.testing.assert_array_equal(d.inter_prism_distance, est.inter_prism_distance)
    np.testing.assert_array_equal(distance_outliers(d, ref, 0.05), [False, True, True, False])


# --- simulated deployments ------------------------------------------------------------------

def _wrap(a: np.ndarray) -> np.ndarray:
    return a - 2 * np.pi * np.round(a / (2 * np.pi))


def _quiet_window(sim, length: float = WINDOW_S, margin: float = 5.0) -> tuple[float, float]:
    """The first window after mid-run in which every station tracks without a gap > 1 s."""
    t = sim.observations[0].t
    for t0 in np.arange(t[0] + 0.4 * (t[-1] - t[0]), t[-1] - length - margin, 1.0):
        spans = [o.t[(o.t >= t0 - margin) & (o.t <= t0 + length + margin)]
                 for o in sim.observations]
        if all(s.size > 2 and s[0] < t0 - margin + 1 and s[-1] > t0 + length + margin - 1
               and np.max(np.diff(s)) < 1.0 for s in spans):
            return float(t0), float(t0 + length)
    raise AssertionError("no window where every station tracks")


def _wrong_prism(sim, station: str, point_robot, t0: float, t1: float):
    """``sim`` with ``station`` measuring ``point_robot`` (a point of the robot frame) instead
    of its prism from ``t0`` to ``t1``: the true polar values of that point, plus the noise the
    station's own measurements had."""
    obs = list(sim.observations)
    k = [o.station for o in obs].index(station)
    o, truth = obs[k], sim.truth.observations[station]
    m = (o.t >= t0) & (o.t <= t1)
    R, p = sim.truth.model.robot_at(truth.t_true[m])
    world = np.einsum("nij,j->ni", R, np.asarray(point_robot, dtype=float)) + p
    hz, v, dist = cartesian_to_polar(sim.truth.T_world_station[station].inverse().apply(world))
    d = dist / (1 + truth.ppm[m] * 1e-6) - sim.config.additive_constant_m
    new = {"hz": o.hz.copy(), "v": o.v.copy(), "d": o.d.copy()}
    new["hz"][m] = np.mod(hz + _wrap(o.hz[m] - truth.hz[m]), 2 * np.pi)
    new["v"][m] = v + (o.v[m] - truth.v[m])
    new["d"][m] = d + (o.d[m] - truth.d[m])
    obs[k] = replace(o, **new)
    return replace(sim, observations=obs)


def _cut(sim, t0: float, t1: float):
    """``sim`` without any measurement from ``t0`` to ``t1``."""
    return replace(sim, observations=[o.select(~((o.t >= t0) & (o.t <= t1)))
                                      for o in sim.observations])


def _run(sim, path: Path, seed: int, **options):
    data, opts = load_deployment(write_deployment(sim, path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run_pipeline(data, opts.updated(seed=seed, engine="mc", samples=300, **options))


def _median_sigma_mm(record) -> float:
    cov = record.groundtruth.cov
    return float(np.median(np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2))) * 1e3)


def _median_prism_sigma_mm(record, prism: str) -> float:
    cov = record.prisms_cov[:, list(record.prism_ids).index(prism)]
    return float(np.median(np.sqrt(np.trace(cov, axis1=1, axis2=2))) * 1e3)


def _nees_per_dof(sim, record) -> float:
    gt = record.groundtruth
    p, q = sim.truth_at(gt.t)
    return float(compare_to_truth(gt, p, q).nees_position.values.mean() / 3)


def _runs(tmp: Path, seed: int, **options) -> dict:
    sim = simulate_deployment(SimulationConfig(duration_s=180.0), np.random.default_rng(seed))
    t0, t1 = _quiet_window(sim)
    bad = _wrong_prism(sim, "2", SPARE_PRISM_ROBOT_M, t0, t1)
    return {"sim": sim, "window": (t0, t1),
            "new": _run(bad, tmp / "new", seed, **options),
            "old": _run(bad, tmp / "old", seed, outlier_windows="keep", **options),
            "cut": _run(_cut(sim, t0, t1), tmp / "cut", seed, **options)}


@pytest.fixture(scope="module")
def classes(tmp_path_factory):
    """The default options (Qc scaled per motion class)."""
    return _runs(tmp_path_factory.mktemp("classes"), 21)


@pytest.fixture(scope="module")
def constant(tmp_path_factory):
    """One Qc per track (the paper's): the outliers' Qc then sets the wrong prism's sigma at
    every pose, and every pose's sigma with it."""
    return _runs(tmp_path_factory.mktemp("constant"), 22, motion_prior="constant")


@pytest.mark.slow
@pytest.mark.parametrize("which", ["classes", "constant"])
def test_the_wrong_prism_is_rejected_by_the_distance_gate(which, request):
    runs = request.getfixturevalue(which)
    t0, t1 = runs["window"]
    for name in ("new", "old"):
        rec = runs[name]
        inside = (rec.prisms_t > t0 + 1.0) & (rec.prisms_t < t1 - 1.0)
        rejected = dict(zip(rec.rejected_t, rec.rejected_reason, strict=True))
        assert inside.sum() > 50
        assert all(rejected.get(t) == "distance" for t in rec.prisms_t[inside]), name
        assert not np.any((rec.groundtruth.t > t0) & (rec.groundtruth.t < t1)), name
    # one window, around the injected one; every prism's measurements in it left out
    report = runs["new"].computation.filter_reports["module4"]
    assert report.n_blocks == 1 and report.fits >= 1 and report.converged
    (a, b), = report.windows
    assert t0 - 1.0 < a < t0 + 1.0 and t1 - 1.0 < b < t1 + 1.0
    assert all(c["distance_window"] > 20 for c in report.per_series)
    assert "module4" not in runs["old"].computation.filter_reports


@pytest.mark.parametrize("which", ["classes", "constant"])
def test_qc_and_sigma_match_the_cut_input_and_the_old_behaviour_does_not(which, request):
    runs = request.getfixturevalue(which)
    new, old, cut = runs["new"], runs["old"], runs["cut"]
    for pid in cut.qc:
        ratio = np.diag(new.qc[pid]) / np.diag(cut.qc[pid])
        np.testing.assert_allclose(ratio[:2], 1.0, rtol=QC_RTOL, err_msg=f"prism {pid}")
        np.testing.assert_allclose(ratio[2], 1.0, rtol=QC_VERTICAL_RTOL, err_msg=f"prism {pid}")
    # the old behaviour: the wrong prism's jumps inflate its Qc by orders of magnitude
    assert np.min(np.diag(old.qc["2"]) / np.diag(cut.qc["2"])) > 10.0
    sig = {k: _median_sigma_mm(runs[k]) for k in ("new", "old", "cut")}
    assert sig["new"] == pytest.approx(sig["cut"], rel=SIGMA_RTOL)
    if which == "constant":  # one Qc per track: the old run's sigmas are inflated too
        # the wrong prism's own (the registration leans on the other two prisms, more so the
        # weighted one: the poses' sigmas grow less, but out of the new run's tolerance)
        prism = {k: _median_prism_sigma_mm(runs[k], "2") for k in ("old", "cut")}
        assert prism["old"] > 1.5 * prism["cut"]
        assert sig["old"] > (1.0 + SIGMA_RTOL) * sig["cut"]
    # the kept poses stay as honest as those of the cut input
    nees = {k: _nees_per_dof(runs["sim"], runs[k]) for k in ("new", "cut")}
    assert nees["new"] == pytest.approx(nees["cut"], rel=0.15)
    assert nees["new"] < 3.0


def test_the_run_directory_counts_what_was_left_out(classes, tmp_path):
    rec = classes["new"]
    report = rec.computation.filter_reports["module4"]
    left = rec.removed.stage == "module4"
    assert left.sum() == report.removed["distance_window"] == report.n_in - report.n_kept
    assert set(rec.removed.reason[left]) == {"distance_window"}
    a, b = report.windows[0]
    assert np.all((rec.removed.t[left] > a) & (rec.removed.t[left] < b))
    # the tracks the GPs were fitted to hold none of them
    for pid, tr in rec.measurements.items():
        assert not np.any((tr.t > a) & (tr.t < b)), pid
    out = write_run(rec, tmp_path / "run")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["parameters"]["outlier_windows"] == "remove"
    entry = summary["filters"]["module4"]
    assert entry["removed"] == {"distance_window": int(left.sum())}
    assert entry["fits"] == report.fits and len(entry["windows_s"]) == 1
    back = read_run(out)
    assert back.options.interpolation.outlier_windows == "remove"
    assert int(np.sum(back.removed.stage == "module4")) == int(left.sum())


def test_a_run_without_distance_rejections_is_unchanged(tmp_path):
    sim = simulate_deployment(SimulationConfig(duration_s=90.0), np.random.default_rng(23))
    new = _run(sim, tmp_path / "new", 23)
    old = _run(sim, tmp_path / "old", 23, outlier_windows="keep")
    assert "distance" not in set(new.rejected_reason)
    assert "outlier_windows" not in new.computation.timings_s
    assert "module4" not in new.computation.filter_reports
    for a, b in ((new.groundtruth.t, old.groundtruth.t),
                 (new.groundtruth.position, old.groundtruth.position),
                 (new.groundtruth.quat_xyzw, old.groundtruth.quat_xyzw),
                 (new.groundtruth.cov, old.groundtruth.cov), (new.prisms_cov, old.prisms_cov),
                 (new.rejected_t, old.rejected_t), (new.removed.t, old.removed.t)):
        np.testing.assert_array_equal(a, b)
    for pid in new.qc:
        np.testing.assert_array_equal(new.qc[pid], old.qc[pid])
