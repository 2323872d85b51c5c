"""The stages of a run (rtsgt.stages; docs/pipeline.md): one chain from prisms to gated poses,
the per-time rows taken and merged, and a pipeline that only orders the stages."""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rtsgt.filtering.gates import apply_gates
from rtsgt.interpolation.prisms import PrismsAtTimes
from rtsgt.options import RunOptions, stage_rng
from rtsgt.pose import ReferencePoints, estimate_poses
from rtsgt.stages.poses import assemble_rows, gated_poses, pose_estimate, take_rows

SRC = Path(__file__).resolve().parents[1] / "src" / "rtsgt"


def _prisms(rng: np.random.Generator, T: int = 30) -> tuple[PrismsAtTimes, ReferencePoints]:
    """Three prisms on a rig at T poses, 1 mm noise, the prism 2 of pose 4 moved by 0.3 m."""
    ref = ReferencePoints(("a", "b", "c"), np.array([[0.4, 0.0, 0.1], [-0.3, 0.35, 0.12],
                                                     [-0.2, -0.4, 0.08]]),
                          np.tile(np.eye(3) * 1e-6, (3, 1, 1)))
    R = Rotation.from_rotvec(rng.normal(0, 0.5, (T, 3))).as_matrix()
    t = rng.normal(0, 20, (T, 3))
    xyz = np.einsum("tij,nj->tni", R, ref.xyz) + t[:, None] + rng.normal(0, 1e-3, (T, 3, 3))
    xyz[4, 2] += [0.3, 0.0, 0.0]
    cov = np.tile(np.eye(3) * 1e-6, (T, 3, 1, 1))
    pr = PrismsAtTimes(np.arange(T) * 0.2, xyz, cov, 0.5 * cov, {"instrument": cov},
                       rng.uniform(0, 0.1, (T, 3)))
    return pr, ref


def test_gated_poses_is_the_run_pose_step_and_its_gates():
    pr, ref = _prisms(np.random.default_rng(3))
    options = RunOptions(seed=11).updated(engine="mc", samples=200)
    got = gated_poses(pr, ref, options, "sqrt_trace")
    # the same step written out: the run's engine, its "pose" stream, the run's gates
    want = estimate_poses(pr.xyz, pr.cov, ref, engine="mc", samples=200,
                          registration=options.pose.registration, rng=stage_rng(11, "pose"))
    keep, report = apply_gates(want, ref, distance_gate_m=options.pose.distance_gate_m,
                               uncertainty_gate_m=options.pose.uncertainty_gate_m,
                               uncertainty_measure="sqrt_trace")
    np.testing.assert_array_equal(got.estimate.cov, want.cov)
    np.testing.assert_array_equal(got.keep, keep)
    assert got.report.uncertainty_measure == "sqrt_trace"
    assert not got.keep[4] and got.report.reason[4] == "distance" and got.keep.sum() == 29
    # the stream is drawn afresh at each call: the same draws again
    again = pose_estimate(pr.xyz, pr.cov, ref, options)
    np.testing.assert_array_equal(again.cov, want.cov)
    # the planner's linear step ignores the run's engine
    lin = pose_estimate(pr.xyz, pr.cov, ref, options, engine="linear")
    assert lin.engine == "linear" and not np.array_equal(lin.cov, want.cov)


def test_rows_taken_then_assembled_give_the_result_back():
    pr, _ = _prisms(np.random.default_rng(5), T=12)
    first = np.array([1, 0, 0, 1, 1, 0, 1, 0, 0, 0, 1, 0], bool)
    back = assemble_rows(take_rows(pr, first), take_rows(pr, ~first), first)
    for name in ("t", "xyz", "cov", "cov_gp", "nearest_dt"):
        np.testing.assert_array_equal(getattr(back, name), getattr(pr, name))
    np.testing.assert_array_equal(back.cov_by_source["instrument"], pr.cov_by_source["instrument"])
    assert back.cov_joint is None
    assert take_rows(pr, first).xyz.shape == (5, 3, 3)


def test_results_that_differ_beyond_their_rows_are_not_merged():
    @dataclass(frozen=True)
    class Rows:
        x: np.ndarray
        engine: str

    with pytest.raises(ValueError, match="differ"):
        assemble_rows(Rows(np.zeros(1), "mc"), Rows(np.ones(1), "linear"), np.array([True, False]))


def _functions(tree: ast.AST):
    return [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def _calls(node: ast.AST) -> set[str]:
    return {n.func.id if isinstance(n.func, ast.Name) else getattr(n.func, "attr", "")
            for n in ast.walk(node) if isinstance(n, ast.Call)}


def test_the_pipeline_only_orders_the_stages():
    files = [SRC / "pipeline.py", *sorted((SRC / "stages").glob("*.py"))]
    assert len((SRC / "pipeline.py").read_text().splitlines()) <= 300
    for path in files:
        tree = ast.parse(path.read_text())
        for f in _functions(tree):
            assert f.end_lineno - f.lineno + 1 <= 80, f"{path.name}: {f.name} is too long"
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module.startswith("rtsgt"):
                assert not any(a.name.startswith("_") for a in node.names), path.name
                if path.parent.name == "stages":  # below the pipeline and its users
                    top = node.module.split(".")[1]
                    assert top not in ("pipeline", "evaluation", "planning", "io", "cli",
                                       "report", "batch"), f"{path.name} imports {node.module}"
    # the pose step and the gates are called in one module only
    for path in files:
        if path.name != "poses.py":
            calls = _calls(ast.parse(path.read_text()))
            assert not calls & {"estimate_poses", "apply_gates"}, path.name


def test_the_continuous_ground_truth_and_the_planner_go_through_the_chain():
    gt = ast.parse((SRC / "evaluation" / "groundtruth.py").read_text())
    query = next(f for f in _functions(gt) if f.name == "query_poses")
    assert "gated_poses" in _calls(query)
    assert not _calls(query) & {"estimate_poses", "apply_gates"}
    plan = _calls(ast.parse((SRC / "planning" / "predict.py").read_text()))
    assert "pose_estimate" in plan and "estimate_poses" not in plan
