"""End to end: simulated deployments with known truth, and the real excerpt."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_output import write_run
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "rts_20221110"
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "rts_20221110" / "deployment.toml"


def _simulate_and_run(tmp_path: Path, seed: int, duration: float, **options):
    sim = simulate_deployment(SimulationConfig(duration_s=duration), np.random.default_rng(seed))
    cfg = write_deployment(sim, tmp_path / f"dep{seed}")
    data, opts = load_deployment(cfg)
    import dataclasses

    opts = dataclasses.replace(opts, seed=seed, **options)
    result = run_pipeline(data, opts)
    p, q = sim.truth_at(result.groundtruth.t)
    return sim, result, compare_to_truth(result.groundtruth, p, q)


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("demo")
    sim, result, cmp = _simulate_and_run(tmp, 11, 180.0, engine="mc", samples=300)
    out = write_run(result, tmp / "run")
    return sim, result, cmp, out


def test_run_directory_files(demo_run):
    sim, result, cmp, out = demo_run
    gt = result.groundtruth
    assert len(gt) > 300
    tum = np.loadtxt(out / "groundtruth.tum")
    assert tum.shape == (len(gt), 8)
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, atol=1e-9)
    header = (out / "groundtruth_covariance.csv").read_text().splitlines()[0].split(",")
    assert header[:8] == ["t", "x", "y", "z", "qx", "qy", "qz", "qw"]
    assert header[8:] == [f"cov_{i}{j}" for i in range(6) for j in range(6)]
    cov = np.loadtxt(out / "groundtruth_covariance.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(cov[:, 8:].reshape(-1, 6, 6), gt.cov, rtol=1e-12)
    for pid in ("1", "2", "3"):
        head = (out / "prisms" / f"prism{pid}.csv").read_text().splitlines()[0]
        assert head == "t,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["parameters"]["seed"] == 11
    assert summary["poses"]["kept"] == len(gt)
    assert set(summary["prisms"]) == {"1", "2", "3"}
    assert "module1_station1" in summary["filters"] and "module2" in summary["filters"]
    assert summary["calibration"]["residuals_mm"]["count"] > 0


def test_groundtruth_is_readable_by_evo(demo_run):
    evo_io = pytest.importorskip("evo.tools.file_interface")
    _, result, _, out = demo_run
    traj = evo_io.read_tum_trajectory_file(str(out / "groundtruth.tum"))
    np.testing.assert_allclose(traj.positions_xyz, result.groundtruth.position, atol=1e-8)


def test_demo_poses_are_accurate_and_reproducible(demo_run, tmp_path):
    _, result, cmp, _ = demo_run
    d = cmp.to_dict()
    # millimetre ground truth: errors of a few mm, and the covariance says as much
    assert d["position_error_mm"]["median"] < 6.0
    sig = np.sqrt(np.trace(result.groundtruth.cov[:, :3, :3], axis1=1, axis2=2))
    assert 0.3 < np.sqrt(np.mean(cmp.position_error_m**2)) / np.sqrt(np.mean(sig**2)) < 2.0
    _, again, _ = _simulate_and_run(tmp_path, 11, 180.0, engine="mc", samples=300)
    np.testing.assert_array_equal(again.groundtruth.cov, result.groundtruth.cov)


def test_existing_output_directory_is_refused(demo_run):
    _, result, _, out = demo_run
    with pytest.raises(InputError, match="exists; use --force"):
        write_run(result, out)
    before = sorted(p.name for p in out.iterdir())
    write_run(result, out, force=True)
    assert sorted(p.name for p in out.iterdir()) == before
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".run.tmp")]


@pytest.mark.skipif(not SHARED.is_dir(), reason="shared/data/rts_20221110 is not beside this checkout")
def test_real_excerpt_end_to_end(tmp_path):
    data, opts = load_deployment(EXAMPLE)
    import dataclasses

    result = run_pipeline(data, dataclasses.replace(opts, samples=300))
    gt = result.groundtruth
    assert len(gt) > 100
    # the registered prisms keep the reference inter-prism distances (DESIGN.md section 9)
    ref = np.array([0.73555, 0.90303, 1.03046])
    kept = result.estimate.inter_prism_distance[result.keep]
    dev = np.abs(kept - ref)
    assert np.median(dev) < 0.005
    out = write_run(result, tmp_path / "real")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["poses"]["kept"] == len(gt)
    assert summary["parameters"]["instrument"] == "trimble-s7"
