"""End to end: simulated deployments with known truth, and the real excerpt."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _paths import EXAMPLE_TOML as EXAMPLE
from rtsgt.errors import InputError
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import write_run
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth


def _simulate_and_run(tmp_path: Path, seed: int, duration: float, **options):
    sim = simulate_deployment(SimulationConfig(duration_s=duration), np.random.default_rng(seed))
    cfg = write_deployment(sim, tmp_path / f"dep{seed}")
    data, opts = load_deployment(cfg)

    opts = opts.updated(seed=seed, **options)
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
    assert summary["schema"] == {"name": "rtsgt-run", "version": 1}
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
    with pytest.raises(InputError, match="exists and is not empty; use --force"):
        write_run(result, out)
    before = sorted(p.name for p in out.iterdir())
    write_run(result, out, force=True)
    assert sorted(p.name for p in out.iterdir()) == before
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # nothing left aside


def test_real_excerpt_end_to_end(tmp_path):
    data, opts = load_deployment(EXAMPLE)

    result = run_pipeline(data, opts.updated(samples=300))
    gt = result.groundtruth
    assert len(gt) > 100
    # the registered prisms keep the reference inter-prism distances
    # (docs/paper-figures.md#the-real-excerpt)
    ref = np.array([0.73555, 0.90303, 1.03046])
    kept = result.computation.estimate.inter_prism_distance[result.computation.keep]
    dev = np.abs(kept - ref)
    assert np.median(dev) < 0.005
    out = write_run(result, tmp_path / "real")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["poses"]["kept"] == len(gt)
    assert summary["parameters"]["instrument"] == "trimble-s7"
    # the 24 hourly ECCC records of 2022-11-10 cover the 10:44 (local) tracking
    w = summary["weather"]
    assert w["file"].endswith("weather_ECCC_raw_excerpt.csv") and w["records"] == 24
    assert w["covered"] is True and w["first_utc"] == "2022-11-10 05:00:00"
    # the surveyed distances are compared with the tracked ones, pair by pair
    pairs = summary["inter_prism_distances"]
    assert set(pairs) == {"1-2", "1-3", "2-3"}
    for p, d in zip(("1-2", "1-3", "2-3"), ref, strict=True):
        assert pairs[p]["surveyed_m"] == pytest.approx(d, abs=1e-5)
        assert pairs[p]["poses"] == len(gt) and np.isfinite(pairs[p]["ratio"])
    assert isinstance(summary["warnings"], list)


def test_station_coupling_reproduces_the_sampled_cross_covariance_of_prisms(tmp_path):
    """Two stations calibrated from the same reference shots have correlated errors: the joint
    prism covariance's off-diagonal block equals the cross-covariance of prism positions mapped
    by the calibration's own Monte Carlo samples (first order, so to a small relative error)."""
    import warnings

    from rtsgt.calibration import calibrate
    from rtsgt.noise.coupling import StationCoupling, joint_prism_covariance

    sim = simulate_deployment(SimulationConfig(duration_s=30.0), np.random.default_rng(5))
    data, _ = load_deployment(write_deployment(sim, tmp_path / "dep"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        calib = calibrate(data.gcp, reference_station="1", instrument=data.instrument,
                          samples=4000, rng=np.random.default_rng(1))
    coupling = StationCoupling.from_calibration(calib)
    assert set(coupling.cross) == {("1", "1"), ("1", "2"), ("1", "3"), ("2", "2"), ("2", "3"),
                                   ("3", "3")}
    np.testing.assert_array_equal(coupling.cross[("1", "2")], 0.0)  # the reference is exact
    # a prism 40 m from station 2 and one 60 m from station 3 (station frames)
    T2, T3 = calib.transforms["2"], calib.transforms["3"]
    p2, p3 = np.array([30.0, 25.0, 2.0]), np.array([-40.0, 44.0, -1.0])
    w2 = np.einsum("mij,j->mi", T2.samples_rotation, p2) + T2.samples_translation
    w3 = np.einsum("mij,j->mi", T3.samples_rotation, p3) + T3.samples_translation
    sampled = (w2 - w2.mean(0)).T @ (w3 - w3.mean(0)) / (w2.shape[0] - 1)
    xyz = np.stack([T2.rotation @ p2 + T2.translation, T3.rotation @ p3 + T3.translation])[None]
    zero = np.zeros((1, 2, 3, 3))
    joint = joint_prism_covariance(xyz, zero, zero, ["2", "3"], coupling)[0]
    assert np.linalg.norm(sampled) > 1e-8  # a real correlation, not a zero
    np.testing.assert_allclose(joint[:3, 3:], sampled, rtol=0, atol=0.02 * np.abs(sampled).max())
    np.testing.assert_allclose(joint[3:, :3], sampled.T, rtol=0, atol=0.02 * np.abs(sampled).max())
    s22 = np.cov(w2, rowvar=False)  # the diagonal block: the calibration part of prism 2
    np.testing.assert_allclose(joint[:3, :3], s22, rtol=0, atol=0.02 * np.abs(s22).max())
    assert np.linalg.eigvalsh(joint).min() > -1e-12 * np.abs(joint).max()
    # round trip through summary.json
    back = StationCoupling.from_dict(json.loads(json.dumps(coupling.to_dict())))
    np.testing.assert_array_equal(back.cross[("2", "3")], coupling.cross[("2", "3")])


def test_rate_gates_too_tight_for_the_robot_are_reported(tmp_path):
    """The paper's 1 deg/s gates on a 0.5-2 m/s robot passing 8 m from the stations: module 1
    rejects true motion, and the run says so (with the configuration keys to change)."""

    from rtsgt.filtering import FilterParams

    sim = simulate_deployment(SimulationConfig(duration_s=120.0), np.random.default_rng(11))
    data, opts = load_deployment(write_deployment(sim, tmp_path / "dep"))
    with pytest.warns(UserWarning, match=r"rejected \d+ of \d+ measurements .* \[filter\]"):
        run_pipeline(data, opts.updated(filter=FilterParams(), engine="linear"))
    # with the simulator's gates (from its robot's speed limits) nothing is said
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_pipeline(data, opts.updated(engine="linear"))
    assert not [w for w in caught if "module 1 rejected" in str(w.message)]


def test_gp_noise_all_runs_on_a_simulated_deployment(tmp_path):
    """The paper's setting (the GP given the total covariance) runs end to end: the prisms are
    then taken as independent (the calibration's cross-covariance between stations would not
    fit the diagonal blocks the GP has averaged), the covariance is positive definite, and the
    poses are as accurate as their sigma says to within the paper's own optimism (the GP
    averages the systematic errors away, so the NEES is not 1; it is bounded)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, result, cmp = _simulate_and_run(tmp_path, 1, 60.0, engine="linear", samples=100,
                                           gp_noise="all")
    assert result.computation.prisms.cov_joint is None
    assert len(result.groundtruth.t) > 100
    assert np.linalg.eigvalsh(result.groundtruth.cov).min() > 0
    err = np.linalg.norm(cmp.error[:, :3], axis=1)
    assert np.median(err) < 0.01  # metres: the poses themselves are fine


def test_a_run_written_by_two_processes_is_the_same_run(demo_run, tmp_path, monkeypatch):
    """The command line writes the ground truth's covariances in a forked child beside the
    rest (rtsgt.io.run_dir.WRITE_PROCESSES = 2): every file byte for byte as one process
    writes it."""
    from rtsgt.io import run_dir

    _, result, _, out = demo_run
    monkeypatch.setattr(run_dir, "WRITE_PROCESSES", 2)
    two = write_run(result, tmp_path / "two")
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(two) for p in two.rglob("*") if p.is_file())
    for rel in files:
        if rel.name != "summary.json":  # it records where the run was written
            assert (out / rel).read_bytes() == (two / rel).read_bytes(), rel


def test_a_writer_child_that_fails_fails_the_run_and_leaves_nothing(demo_run, tmp_path,
                                                                     monkeypatch):
    """The child's error reaches the parent, which leaves no output behind."""
    import os

    from rtsgt.io import run_dir

    pids = tmp_path / "pids"
    pids.mkdir()

    def full(path, split):
        (pids / str(os.getpid())).touch()
        raise OSError(f"No space left on device: {path.name}")

    _, result, _, _ = demo_run
    monkeypatch.setattr(run_dir, "WRITE_PROCESSES", 2)
    monkeypatch.setattr(run_dir, "_write_split", full)
    with pytest.raises(OSError, match="No space left on device: groundtruth_shared.csv"):
        write_run(result, tmp_path / "out" / "run")
    assert [p.name for p in pids.iterdir()] != [str(os.getpid())]  # it failed in the child
    assert not (tmp_path / "out").exists() or list((tmp_path / "out").iterdir()) == []
