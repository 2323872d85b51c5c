"""APE and RPE equal evo's on the same data, for every alignment both tools offer.

evo (GPL) is a test-only dependency, used here as an independent reference implementation:
its Python API (``evo.main_ape.ape``, ``evo.main_rpe.rpe``) and its command-line tools
(``evo_ape``, ``evo_rpe`` on TUM files written by rtsgt). rtsgt never imports it.
"""

from __future__ import annotations

import copy
import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rtsgt.evaluation import evaluate
from rtsgt.io.trajectory import write_tum
from rtsgt.types import PoseTrajectory
from test_evaluation_synth import smooth_truth, trajectory, transform_trajectory

evo_metrics = pytest.importorskip("evo.core.metrics")
from evo import main_ape, main_rpe  # noqa: E402
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402

STATS = ("rmse", "mean", "median", "std", "min", "max")
TOL = 1e-9

#: rtsgt alignment -> evo keyword arguments (evo has no 4dof)
EVO_ALIGN = {
    "none": {},
    "se3": {"align": True},
    "sim3": {"align": True, "correct_scale": True},
    "scale": {"correct_scale": True},
    "origin": {"align_origin": True},
}


@pytest.fixture(scope="module")
def pair():
    """Ground truth and a noisy, drifting estimate in another frame with another scale."""
    rng = np.random.default_rng(42)
    t, p, R = smooth_truth(600)
    gt = trajectory(t, p, R)
    drift = np.cumsum(rng.normal(0, 0.01, (len(t), 3)), axis=0)
    rot_noise = Rotation.from_rotvec(
        np.cumsum(rng.normal(0, 2e-3, (len(t), 3)), axis=0)
    ).as_matrix()
    est_world = trajectory(t, p + drift, rot_noise @ R)
    Ra = Rotation.from_rotvec([0.3, -0.2, 1.9]).as_matrix()
    est = transform_trajectory(est_world, Ra, np.array([5.0, -3.0, 1.0]), s=0.7)
    return gt, est


def to_evo(traj: PoseTrajectory) -> PoseTrajectory3D:
    return PoseTrajectory3D(traj.position.copy(), np.roll(traj.quat_xyzw, 1, axis=1), traj.t.copy())


def assert_stats(evo_stats: dict, mine, label: str) -> None:
    for k in STATS:
        assert abs(evo_stats[k] - getattr(mine, k)) <= TOL * max(1.0, abs(evo_stats[k])), (
            f"{label} {k}: evo {evo_stats[k]!r} rtsgt {getattr(mine, k)!r}"
        )


@pytest.mark.parametrize("align", sorted(EVO_ALIGN))
def test_ape_equals_evo(pair, align):
    gt, est = pair
    res = evaluate(gt, est, align=align)
    PR = evo_metrics.PoseRelation
    for rel, mine in (
        (PR.translation_part, res.ape.translation_m),
        (PR.rotation_angle_deg, res.ape.rotation_deg),
        (PR.full_transformation, res.ape.full),
    ):
        r = main_ape.ape(to_evo(gt), to_evo(est), rel, **EVO_ALIGN[align])
        assert_stats(r.stats, mine, f"APE {align} {rel.name}")
        np.testing.assert_allclose(
            r.np_arrays["error_array"],
            {
                "translation_part": res.ape.translation_error,
                "rotation_angle_deg": res.ape.rotation_error_deg,
                "full_transformation": res.ape.full_error,
            }[rel.name],
            rtol=0,
            atol=1e-9,
        )
    if align in ("se3", "sim3"):
        T_evo = main_ape.ape(
            to_evo(gt), to_evo(est), PR.translation_part, **EVO_ALIGN[align]
        ).np_arrays["alignment_transformation_sim3"]
        np.testing.assert_allclose(res.alignment.as_matrix(), T_evo, atol=1e-9)


@pytest.mark.parametrize("align", ["none", "se3", "sim3"])
@pytest.mark.parametrize(
    ("delta", "unit", "all_pairs"),
    [(1.0, "m", False), (2.5, "m", True), (1, "f", False), (7, "f", True)],
)
def test_rpe_equals_evo(pair, align, delta, unit, all_pairs):
    gt, est = pair
    res = evaluate(gt, est, align=align, delta=delta, delta_unit=unit, all_pairs=all_pairs)
    evo_unit = evo_metrics.Unit.meters if unit == "m" else evo_metrics.Unit.frames
    PR = evo_metrics.PoseRelation
    for rel, mine in (
        (PR.translation_part, res.rpe.translation_m),
        (PR.rotation_angle_deg, res.rpe.rotation_deg),
        (PR.full_transformation, res.rpe.full),
    ):
        r = main_rpe.rpe(
            to_evo(gt),
            to_evo(est),
            rel,
            delta=delta,
            delta_unit=evo_unit,
            all_pairs=all_pairs,
            **EVO_ALIGN[align],
        )
        assert len(r.np_arrays["error_array"]) == res.rpe.pairs.shape[0]
        assert_stats(r.stats, mine, f"RPE {align} {delta}{unit} all={all_pairs} {rel.name}")


def test_rpe_pairs_from_reference_and_n_align_equal_evo(pair):
    gt, est = pair
    res = evaluate(
        gt, est, align="se3", n_align=150, delta=3.0, delta_unit="m", pairs_from_reference=True
    )
    PR = evo_metrics.PoseRelation
    r = main_rpe.rpe(
        to_evo(gt),
        to_evo(est),
        PR.translation_part,
        delta=3.0,
        delta_unit=evo_metrics.Unit.meters,
        align=True,
        n_to_align=150,
        pairs_from_reference=True,
    )
    assert_stats(r.stats, res.rpe.translation_m, "RPE n_align pairs_from_reference")
    r = main_ape.ape(to_evo(gt), to_evo(est), PR.rotation_angle_deg, align=True, n_to_align=150)
    assert_stats(r.stats, res.ape.rotation_deg, "APE n_align")


def _evo_cli(tool: str, args: list[str], tmp_path: Path) -> dict:
    exe = shutil.which(tool) or str(Path(sys.executable).parent / tool)
    if not Path(exe).exists():
        pytest.skip(f"{tool} not found")
    out = tmp_path / f"{tool}_{len(list(tmp_path.iterdir()))}.zip"
    subprocess.run(
        [exe, "tum", *args, "--save_results", str(out), "--no_warnings", "--silent"],
        check=True,
        capture_output=True,
        timeout=120,
    )
    with zipfile.ZipFile(out) as z:
        return json.loads(z.read("stats.json"))


def test_evo_command_line_on_tum_files_written_by_rtsgt(pair, tmp_path):
    """The same TUM files through evo_ape / evo_rpe and through rtsgt (file round trip)."""
    from rtsgt.io.trajectory import read_tum

    gt, est = pair
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", est)
    g, e = read_tum(tmp_path / "gt.tum"), read_tum(tmp_path / "est.tum")
    files = [str(tmp_path / "gt.tum"), str(tmp_path / "est.tum")]
    for flags, align in (([], "none"), (["-a"], "se3"), (["-a", "-s"], "sim3")):
        res = evaluate(g, e, align=align, delta=2.0, delta_unit="m")
        s = _evo_cli("evo_ape", files + flags + ["-r", "trans_part"], tmp_path)
        assert_stats(s, res.ape.translation_m, f"evo_ape {align}")
        if align == "sim3":
            s = _evo_cli("evo_ape", files + flags + ["-r", "angle_deg"], tmp_path)
            assert_stats(s, res.ape.rotation_deg, "evo_ape angle sim3")
            s = _evo_cli(
                "evo_rpe", files + flags + ["-r", "trans_part", "-d", "2", "-u", "m"], tmp_path
            )
            assert_stats(s, res.rpe.translation_m, "evo_rpe 2 m sim3")
            res_f = evaluate(g, e, align=align, delta=5, delta_unit="f")
            s = _evo_cli(
                "evo_rpe", files + flags + ["-r", "angle_deg", "-d", "5", "-u", "f"], tmp_path
            )
            assert_stats(s, res_f.rpe.rotation_deg, "evo_rpe 5 f sim3")


def test_interpolated_association_equals_evo_interpolation_sync(pair, tmp_path):
    """Estimate at other times than the ground truth: rtsgt's linear + slerp interpolation
    equals evo's ``--sync_method interpolation`` (same poses kept within max dt)."""
    gt, est = pair
    keep = np.arange(3, len(est) - 3, 4)
    t_est = est.t[keep] + 0.037  # between ground-truth samples (10 Hz)
    e = PoseTrajectory(t_est, est.position[keep], est.quat_xyzw[keep])
    res = evaluate(gt, e, align="se3", max_dt=0.06)
    assert len(res.association) == keep.size
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", e)
    s = _evo_cli(
        "evo_ape",
        [
            str(tmp_path / "gt.tum"),
            str(tmp_path / "est.tum"),
            "-a",
            "-r",
            "trans_part",
            "--sync_method",
            "interpolation",
            "--t_max_diff",
            "0.06",
        ],
        tmp_path,
    )
    assert_stats(s, res.ape.translation_m, "evo_ape interpolation")


def test_time_offset_is_evo_t_offset(pair):
    """A shifted estimate clock recovers the same result with time_offset (evo --t_offset)."""
    gt, est = pair
    shifted = PoseTrajectory(est.t - 12.5, est.position, est.quat_xyzw)
    a = evaluate(gt, est, align="se3")
    b = evaluate(gt, shifted, align="se3", time_offset=12.5)
    assert a.ape.translation_m.rmse == pytest.approx(b.ape.translation_m.rmse, rel=1e-9)
    np.testing.assert_allclose(b.t, shifted.t)


def _evo_pairs(p, delta, unit, all_pairs):
    from evo.core import filters

    poses = [np.block([[np.eye(3), x[:, None]], [np.zeros((1, 3)), 1.0]]) for x in p]
    if unit == "f":
        return filters.filter_pairs_by_index(poses, int(delta), all_pairs)
    return filters.filter_pairs_by_path(poses, delta, delta * 0.1, all_pairs)


def _tie_margin(p: np.ndarray, delta: float) -> float:
    """Smallest ``|path since the last selected pose - delta| / delta`` met by evo's consecutive
    selection (sequential sums, as evo): how far the data stays from an exact tie."""
    acc, margin = 0.0, np.inf
    for step in np.linalg.norm(np.diff(p, axis=0), axis=1):
        acc += float(step)
        margin = min(margin, abs(acc - delta) / delta)
        if acc >= delta:
            acc = 0.0
    return margin


@pytest.mark.parametrize("all_pairs", [False, True])
def test_rpe_pair_selection_equals_evo_on_hard_paths(all_pairs):
    """Stationary stretches (plateaus of the path length), exactly regular steps and random
    steps: the same pairs as evo's filters.

    Consecutive pairs are compared where the data has no tie (a path since the last selected
    pose equal to delta up to rounding, such as 10 x 0.1 m against 1 m): at a tie evo's choice
    depends on the last bit of its one-vector-at-a-time norms, i.e. on the BLAS kernel, and
    rtsgt resolves it on purpose (``test_rpe_pairs_resolve_ties_*`` in test_evaluation.py).
    The regular paths are compared at deltas between two multiples of their step, and every
    consecutive case checks its own distance from a tie. The all-pairs mode has the same
    arithmetic as evo (vectorised norms, cumulative sum; no BLAS) and is compared everywhere.
    """
    from rtsgt.evaluation.metrics import rpe_pairs

    rng = np.random.default_rng(9)
    steps = [
        np.full(300, 0.1),
        np.where(rng.uniform(size=300) < 0.3, 0.0, rng.uniform(0, 0.2, 300)),
        rng.exponential(0.05, 300),
    ]
    paths = []
    for step in steps:
        d = rng.normal(size=(step.size, 3))
        d *= (step / np.maximum(np.linalg.norm(d, axis=1), 1e-300))[:, None]
        paths.append(np.concatenate([[np.zeros(3)], np.cumsum(d, axis=0)]))
    x = np.repeat(np.arange(60) * 0.1, 3)  # a straight line at 0.1 m steps, each pose 3 times
    paths.append(np.c_[x, 0 * x, 0 * x])
    regular = (True, False, False, True)
    for p, reg in zip(paths, regular, strict=True):
        deltas = (1.05, 0.35, 2.05) if reg and not all_pairs else (1.0, 0.3, 2.0)
        for delta, unit in [(d, "m") for d in deltas] + [(4, "f")]:
            if unit == "m" and not all_pairs:
                assert _tie_margin(p, delta) > 1e-6, f"a tie in the data at delta {delta}"
            mine = rpe_pairs(p, None, delta, unit, all_pairs=all_pairs)
            ref = np.array(_evo_pairs(p, delta, unit, all_pairs), dtype=int).reshape(-1, 2)
            assert mine.shape[0] >= 2
            np.testing.assert_array_equal(mine, ref, err_msg=f"{delta} {unit}")


@pytest.mark.parametrize("align", ["none", "se3", "origin"])
def test_given_mounting_equals_evo_on_the_transformed_trajectory(pair, align):
    """An estimate of a sensor mounted by ``T_body_sensor`` (174 deg, 0.5 m), evaluated with
    the mounting given (``mounting=``, ``--mounting``): the APE and RPE are evo's on the
    trajectory moved to the body frame (``transform(T_body_sensor^-1, right_mul=True)``, as
    ``evo_traj --transform_right``)."""
    from rtsgt.geometry.so3 import exp_so3, matrix_to_quat_xyzw

    gt, est = pair
    R_bs = exp_so3(np.radians(174.0) * np.array([0.05, -0.03, 1.0]) / np.linalg.norm(
        [0.05, -0.03, 1.0]))
    lever = np.array([0.3, -0.35, 0.15])
    T_bs = np.eye(4)
    T_bs[:3, :3], T_bs[:3, 3] = R_bs, lever
    # the estimate seen by a sensor: T_E_sensor = T_E_body T_body_sensor
    sensor = PoseTrajectory(est.t, est.position + est.rotation @ lever,
                            matrix_to_quat_xyzw(est.rotation @ R_bs))
    res = evaluate(gt, sensor, align=align, delta=2.0, delta_unit="m",
                   mounting=(*lever, *matrix_to_quat_xyzw(R_bs)))
    moved = to_evo(sensor)
    moved.transform(np.linalg.inv(T_bs), right_mul=True)
    PR = evo_metrics.PoseRelation
    for rel, mine in ((PR.translation_part, res.ape.translation_m),
                      (PR.rotation_angle_deg, res.ape.rotation_deg)):
        r = main_ape.ape(to_evo(gt), copy.deepcopy(moved), rel, **EVO_ALIGN[align])
        assert_stats(r.stats, mine, f"APE {align} {rel.name} with the mounting")
        r = main_rpe.rpe(to_evo(gt), copy.deepcopy(moved), rel, delta=2.0,
                         delta_unit=evo_metrics.Unit.meters, **EVO_ALIGN[align])
        assert_stats(r.stats, {PR.translation_part: res.rpe.translation_m,
                               PR.rotation_angle_deg: res.rpe.rotation_deg}[rel],
                     f"RPE {align} {rel.name} with the mounting")
    np.testing.assert_allclose(res.ape.translation_m.rmse,
                               evaluate(gt, est, align=align).ape.translation_m.rmse, rtol=1e-9)
