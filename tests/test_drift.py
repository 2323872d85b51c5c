"""Drift by segment length (rtsgt.evaluation.drift): the KITTI devkit's translational and
rotational errors against an independent loop implementation of the devkit's definition, the
lengths of short runs, the per-second drift, the ground truth's floor (statistically), the
position-only ground truth, and the drift in the JSON, the table, the figure and evo's zips.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from rtsgt.cli.main import app
from rtsgt.evaluation import evaluate, evaluate_positions
from rtsgt.evaluation.drift import (
    KITTI_LENGTHS_M,
    ROTATION_DRIFT_NOT_ESTIMABLE,
    distance_lengths,
    drift_metrics,
    kitti_errors,
)
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.io.evo_results import DRIFT_ARRAYS, DRIFT_STATISTICS, evo_result
from rtsgt.io.trajectory import write_tum
from rtsgt.types import PoseTrajectory, PositionTrajectory
from test_evaluation_synth import (
    perturbed,
    random_covariances,
    smooth_truth,
    trajectory,
    write_gt_dir,
)

runner = CliRunner()


# ------------------------------------------------------------------------------------------
# the reference: the devkit's evaluate_odometry, one segment at a time
# ------------------------------------------------------------------------------------------


def _matrices(R: np.ndarray, p: np.ndarray) -> list[np.ndarray]:
    out = []
    for k in range(len(p)):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R[k], p[k]
        out.append(T)
    return out


def devkit_reference(gt: list[np.ndarray], est: list[np.ndarray], lengths, step: int = 10,
                     along: list[float] | None = None) -> list[tuple[int, int, float, float, float]]:
    """(first, last, length, t_err / L, r_err / L) of every segment, as the devkit computes
    them: trajectoryDistances, lastFrameFromSegmentLength, the pose error and its
    translation and rotation errors; ``along`` replaces the distances (time segments)."""
    if along is None:
        along = [0.0]
        for i in range(1, len(gt)):
            d = gt[i][:3, 3] - gt[i - 1][:3, 3]
            along.append(along[-1] + math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2))
    out = []
    for first in range(0, len(gt), step):
        for L in lengths:
            last = -1
            for i in range(first, len(along)):
                if along[i] > along[first] + L:
                    last = i
                    break
            if last == -1:
                continue
            delta_gt = np.linalg.inv(gt[first]) @ gt[last]
            delta_est = np.linalg.inv(est[first]) @ est[last]
            E = np.linalg.inv(delta_gt) @ delta_est
            d = 0.5 * (E[0, 0] + E[1, 1] + E[2, 2] - 1.0)
            r_err = math.acos(max(min(d, 1.0), -1.0))
            t_err = math.sqrt(E[0, 3] ** 2 + E[1, 3] ** 2 + E[2, 3] ** 2)
            out.append((first, last, L, t_err / L, r_err / L))
    return out


def _drifting(t, p, R, rng, pos_walk=0.02, yaw_walk=2e-4, noise=0.01) -> PoseTrajectory:
    """An odometry: the truth with random walks in position (m per sqrt step) and in
    rotation (rad per sqrt step, mostly yaw) composed along the path, and white noise."""
    n = len(t)
    dphi = np.cumsum(rng.normal(size=(n, 3)) * np.array([0.2, 0.2, 1.0]) * yaw_walk, axis=0)
    Rd = Rotation.from_rotvec(dphi).as_matrix()
    steps = np.diff(p, axis=0, prepend=p[:1])
    pd = np.cumsum(np.einsum("nij,nj->ni", Rd, steps), axis=0) + p[0]
    pd += np.cumsum(rng.normal(size=(n, 3)) * pos_walk, axis=0) + noise * rng.normal(size=(n, 3))
    return trajectory(t, pd, Rd @ R)


def _drive(n: int, speed: float, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A car-like drive at 10 Hz: ``speed`` m/s, smoothly turning, gently pitching."""
    t = 1.7e9 + 0.1 * np.arange(n)
    yaw = np.cumsum(0.02 * np.sin(np.arange(n) / 90.0) + 0.004 * rng.normal(size=n))
    pitch = 0.03 * np.sin(np.arange(n) / 70.0)
    v = speed * np.c_[np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)]
    p = np.cumsum(0.1 * v, axis=0)
    R = Rotation.from_euler("ZYX", np.c_[yaw, -pitch, np.zeros(n)]).as_matrix()
    return t, p, R


def _compare(seg, ref, which_lengths):
    """The vectorised segments, per-segment errors, per-length and pooled means against the
    reference: translations to 1e-9 relative; rotation angles to 1e-9 relative plus the
    resolution of the devkit's acos at small angles (an angle theta only to about
    1e-16 / theta rad, from the rounding of the trace: 1-s segments turn by 1e-4 rad), so that
    every value in the units shown (%, deg/m, m/s, deg/s) agrees to 1e-9 absolute."""
    got = sorted(zip(seg.segments.first, seg.segments.last, seg.lengths[seg.segments.which],
                     seg.translation_error, seg.rotation_error, strict=True))
    ref = sorted(ref)
    assert [(int(a), int(b)) for a, b, *_ in got] == [(a, b) for a, b, *_ in ref]
    np.testing.assert_allclose([g[3] for g in got], [r[3] for r in ref], rtol=1e-9, atol=0)
    angle = np.array([g[4] * g[2] for g in got])
    angle_ref = np.array([r[4] * r[2] for r in ref])
    assert np.all(np.abs(angle - angle_ref) <= 1e-9 * angle_ref + 2e-15 / angle_ref)
    for k, L in enumerate(which_lengths):
        rows = [r for r in ref if r[2] == L]
        assert seg.n[k] == len(rows)
        np.testing.assert_allclose(seg.translation[k], np.mean([r[3] for r in rows]), rtol=1e-9)
        np.testing.assert_allclose(seg.rotation[k], np.mean([r[4] for r in rows]), rtol=1e-9,
                                   atol=1e-11)
    np.testing.assert_allclose(seg.translation_all, np.mean([r[3] for r in ref]), rtol=1e-9)
    np.testing.assert_allclose(seg.rotation_all, np.mean([r[4] for r in ref]), rtol=1e-9,
                               atol=1e-11)
    shown = seg.to_dict()
    unit = "deg_per_m" if seg.kind == "distance" else "deg_per_s"
    assert abs(shown[f"rotation_{unit}"] - np.degrees(np.mean([r[4] for r in ref]))) < 1e-9


def test_kitti_lengths_equal_the_devkit_reference():
    """A 1.3 km drive (10 m/s, 1300 poses) and a drifting odometry in another world frame,
    through :func:`evaluate` (SE(3) alignment, which the relative poses do not see): KITTI's
    100-800 m, every segment, its errors and the averages equal the devkit's to 1e-9."""
    rng = np.random.default_rng(240)
    t, p, R = _drive(1300, 10.0, rng)
    est = _drifting(t, p, R, rng, yaw_walk=2e-3)
    A = Rotation.from_rotvec([0.1, -0.2, 2.0]).as_matrix()
    moved = trajectory(t, est.position @ A.T + [5.0, -3.0, 1.0], A @ est.rotation)
    res = evaluate(trajectory(t, p, R), moved, align="se3")
    d = res.drift.distance
    assert d.lengths_from == "KITTI" and tuple(d.lengths) == KITTI_LENGTHS_M
    ref = devkit_reference(_matrices(R, p), _matrices(est.rotation, est.position),
                           KITTI_LENGTHS_M)
    # drifting in both parts (angles above 1e-3 rad, where acos resolves them to 1e-13)
    assert len(ref) > 500 and min(r[4] * r[2] for r in ref) > 1e-3
    _compare(d, ref, KITTI_LENGTHS_M)
    out = res.to_dict()["drift"]["distance"]
    assert out["translation_pct"] == pytest.approx(100 * np.mean([r[3] for r in ref]), rel=1e-9)
    assert out["rotation_deg_per_m"] == pytest.approx(
        np.degrees(np.mean([r[4] for r in ref])), rel=1e-9)


def test_short_run_scaled_lengths_and_time_segments_equal_the_reference():
    """A 40 s drive of about 60 m: lengths k s (s the largest 1-2-5 step at most a tenth of
    the path), and the per-second drift over 1, 10 s (60 s is longer than the run, left out),
    each equal to the devkit's definition with the path (time) as the distance."""
    rng = np.random.default_rng(241)
    t, p, R = _drive(400, 1.5, rng)
    est = _drifting(t, p, R, rng, pos_walk=2e-3, yaw_walk=5e-4, noise=2e-3)
    path = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
    lengths, source = distance_lengths(path)
    step = 10.0 ** np.floor(np.log10(path / 10))
    step = max(m * step for m in (1, 2, 5) if m * step <= path / 10)
    np.testing.assert_allclose(lengths, step * np.arange(1, 9), rtol=1e-15)
    assert "scaled" in source and lengths[-1] <= 0.8 * path

    def errors(first, last):
        return kitti_errors(R, p, est.rotation, est.position, first, last)

    drift = drift_metrics(t, p, errors)
    gt_m, est_m = _matrices(R, p), _matrices(est.rotation, est.position)
    _compare(drift.distance, devkit_reference(gt_m, est_m, lengths), lengths)
    assert tuple(drift.time.lengths) == (1.0, 10.0)
    _compare(drift.time, devkit_reference(gt_m, est_m, (1.0, 10.0), along=list(t)), (1.0, 10.0))
    assert distance_lengths(0.0)[0].size == 0
    assert tuple(distance_lengths(1000.0)[0]) == KITTI_LENGTHS_M


def test_floor_is_the_rms_drift_of_a_perfect_estimate():
    """The exact truth against a ground truth with independent errors of known covariance
    (2 mm, 0.5 mrad): the rms of the segments' drift equals the floor the ground truth's
    relative covariance gives (pooled over about 1000 segments of path and 1900 of time);
    a floor that missed one end of the segments, or the heading error at its start, would be
    30 % or more off. The mean drift lies below its floor."""
    rng = np.random.default_rng(242)
    t, p, R = smooth_truth(2000)
    gt = perturbed(t, p, R, random_covariances(len(t), rng, 2e-3, 5e-4), rng)
    res = evaluate(gt, trajectory(t, p, R), align="none")
    for seg in (res.drift.distance, res.drift.time):
        for part in ("translation", "rotation"):
            rms = np.sqrt(np.mean(getattr(seg, f"{part}_error") ** 2))
            assert rms / getattr(seg, f"{part}_floor_all") == pytest.approx(1.0, abs=0.1)
            assert getattr(seg, f"{part}_all") <= getattr(seg, f"{part}_floor_all")
    out = res.to_dict()["drift"]["distance"]
    assert out["translation_below_floor"] and out["rotation_below_floor"]


def test_position_only_ground_truth_translational_drift():
    """A prism with errors of known covariance and a drifting sensor trajectory: the
    translational drift is the world-frame one of the compared points (an independent loop),
    its floor the rms drift of a perfect estimate; the rotational drift is not estimable,
    and the JSON says so."""
    rng = np.random.default_rng(243)
    t, p, R = smooth_truth(1500)
    lever = np.array([0.2, -0.1, 0.4])
    cov = np.broadcast_to(np.diag([2e-3, 3e-3, 5e-3]) ** 2, (t.size, 3, 3)).copy()
    y = p + R @ lever
    gt = PositionTrajectory(t, y + rng.normal(size=y.shape) * [2e-3, 3e-3, 5e-3], cov, "prism")
    est = _drifting(t, p, R, rng, pos_walk=1e-3, yaw_walk=2e-4, noise=1e-3)
    res = evaluate_positions(gt, est, lever, align="none")
    d = res.drift.distance
    pts = est.position + est.rotation @ lever
    for first, last, L, te in zip(d.segments.first, d.segments.last,
                                  d.lengths[d.segments.which], d.translation_error,
                                  strict=True):
        ref = np.linalg.norm((pts[last] - pts[first]) - (gt.position[last] - gt.position[first]))
        assert te == pytest.approx(ref / L, rel=1e-9)
    assert d.rotation is None and d.rotation_floor is None
    out = res.to_dict()["drift"]
    assert out["rotation"] == ROTATION_DRIFT_NOT_ESTIMABLE
    assert out["distance"]["rotation_deg_per_m"] is None
    assert "world frame" in out["definition"]
    perfect = evaluate_positions(gt, trajectory(t, p, R), lever, align="none").drift.distance
    rms = np.sqrt(np.mean(perfect.translation_error ** 2))
    assert rms / perfect.translation_floor_all == pytest.approx(1.0, abs=0.1)


@pytest.fixture(scope="module")
def cli_files(tmp_path_factory):
    """A ground-truth directory (800 poses, covariances) and a drifting estimate."""
    d = tmp_path_factory.mktemp("drift")
    rng = np.random.default_rng(244)
    t, p, R = smooth_truth(800)
    gt = perturbed(t, p, R, random_covariances(len(t), rng, 2e-3, 5e-4), rng)
    est = _drifting(t, p, R, rng, pos_walk=2e-3, yaw_walk=3e-4, noise=2e-3)
    write_tum(d / "est.tum", PoseTrajectory(t, est.position, matrix_to_quat_xyzw(est.rotation)))
    return d, write_gt_dir(d / "run", gt)


def test_drift_in_the_json_table_figure_and_evo_zip(cli_files, tmp_path):
    """``rtsgt evaluate``: the JSON's drift, the table's rows (one per length, the pooled
    one), the drift figure's panels and the evo zip's statistics and arrays, all the same
    numbers; evo's own loader reads the zip."""
    from rtsgt.report.eval_plots import plot_evaluation

    d, gt_dir = cli_files
    zip_path = tmp_path / "ape.zip"
    r = runner.invoke(app, ["evaluate", str(gt_dir), str(d / "est.tum"), "--json",
                            "--save-results", str(zip_path)])
    assert r.exit_code == 0, r.output
    drift = json.loads(r.stdout)["drift"]
    dist = drift["distance"]
    assert len(dist["by_length"]) == 8 and drift["time"]["lengths_s"] == [1.0, 10.0, 60.0]
    assert dist["translation_pct"] > dist["translation_floor_pct"] > 0
    r = runner.invoke(app, ["evaluate", str(gt_dir), str(d / "est.tum")])
    assert r.exit_code == 0, r.output
    assert "Drift by segment length" in r.stdout
    assert f"{dist['translation_pct']:.3g} %" in r.stdout
    first = dist["by_length"][0]
    assert f"{first['length_m']:g} m" in r.stdout

    file_interface = pytest.importorskip("evo.tools.file_interface")
    res = file_interface.load_res_file(str(zip_path))
    for name, (kind, key) in DRIFT_STATISTICS.items():
        assert res.stats[name] == pytest.approx(drift[kind][key], rel=1e-12)
    np.testing.assert_allclose(res.np_arrays["drift_translation_pct"],
                               [row["translation_pct"] for row in dist["by_length"]], rtol=1e-12)
    assert set(DRIFT_ARRAYS) <= set(res.np_arrays)
    assert "scaled to the path" in res.info["drift_lengths"]

    from rtsgt.io.trajectory import read_groundtruth_dir, read_tum

    result = evaluate(read_groundtruth_dir(gt_dir), read_tum(d / "est.tum"))
    plots = plot_evaluation(result, tmp_path / "fig")
    assert {"drift.png", "drift.svg"} <= {f.name for f in plots.files}
    lengths, mean, floor = plots.drift[("distance", "translation")]
    np.testing.assert_allclose(mean, [row["translation_pct"] for row in dist["by_length"]],
                               rtol=1e-9)
    np.testing.assert_allclose(floor, [row["translation_floor_pct"] for row in dist["by_length"]],
                               rtol=1e-9)
    assert set(plots.drift) == {(k, p) for k in ("distance", "time")
                                for p in ("translation", "rotation")}
    stats = evo_result(result).stats
    assert stats["drift_rotation_deg_per_s"] == pytest.approx(
        drift["time"]["rotation_deg_per_s"], rel=1e-9)
