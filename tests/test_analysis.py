"""Per-source noise analysis (rtsgt.report.analysis) and the run-directory reader.

Synthetic runs with closed-form answers: isotropic covariances ``s^2 I`` have
``sqrt(||Sigma||_F) = 3^(1/4) s``; with the reference centroid at the body origin and three
prisms of covariance ``s^2 I`` each, the first-order pose translation covariance is
``s^2 / 3 I`` (the centroid), so ``sqrt(tr) = s``; first-order pose covariances of independent
sources add up. A run written in the documented directory layout must give the same analysis
as the arrays it was written from.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import exp_so3, matrix_to_quat_xyzw
from rtsgt.geometry.transform import check_covariance
from rtsgt.io.run_dir import (
    COV3_NAMES,
    cov3_to_columns,
    read_run,
    station_positions_from_summary,
    write_csv,
)
from rtsgt.noise.sources import NOISE_SOURCES
from rtsgt.options import RunOptions
from rtsgt.pose import ReferencePoints, estimate_poses
from rtsgt.record import RunRecord
from rtsgt.report.analysis import (
    ALL,
    GP,
    PAPER_MEDIANS_MM,
    REFERENCE,
    analyze,
    analyze_dir,
    bin_labels,
    nearest_psd,
    paper_median_mm,
    parse_bins,
    pose_sigmas,
)
from rtsgt.types import PoseTrajectory, PrismTrack

#: Reference prisms in the body frame, centroid at the origin (m).
R_BODY = np.array([[0.45, 0.0, 0.1], [-0.3, 0.35, -0.05], [-0.15, -0.35, -0.05]])
#: Standard deviation (m) of each source at 1 m and its growth with range (m per m).
SIGMA0 = {"instrument": 1.2e-3, "tilt": 3e-5, "atmosphere": 5e-5, "time_sync": 2e-4,
          "calibration": 4e-4}
GROWTH = {"instrument": 5e-6, "tilt": 1e-7, "atmosphere": 1e-6, "time_sync": 0.0,
          "calibration": 2e-5}


def source_sigma(s: str, r: np.ndarray) -> np.ndarray:
    """Isotropic standard deviation (m) of source ``s`` at range ``r`` (m)."""
    return SIGMA0[s] + GROWTH[s] * r


def make_run_data(seed: int = 0, n_meas: int = 240, n_query: int = 150,
                  ref_sigma: float = 2e-4, reject_every: int = 25) -> RunRecord:
    """A synthetic run: a robot driving away from station 1 to ~230 m, three prisms.

    Covariances are isotropic, ``sigma_s(range)^2 I`` per source, and the fit the paper's
    unweighted one, so every number of the analysis has a closed form. Measurements of prism i are 1/3 of a period out of phase; two
    gaps of 5 s are cut from prism 2's measurements.
    """
    rng = np.random.default_rng(seed)
    t0 = 1.7e9
    duration = 240.0
    speed = 230.0 / duration

    def body(t):
        x = 5.0 + speed * (t - t0)
        yaw = 0.2 * np.sin((t - t0) / 40.0)
        R = exp_so3(np.column_stack([np.zeros_like(t), np.zeros_like(t), yaw]))
        p = np.column_stack([x, 3.0 * np.sin((t - t0) / 30.0), 0.1 * np.ones_like(t)])
        return R, p

    stations = {"1": np.zeros(3), "2": np.array([2.0, -8.0, 0.3]),
                "3": np.array([-4.0, 6.0, -0.2])}
    ids = ("1", "2", "3")
    measurements = {}
    for i, pid in enumerate(ids):
        t = t0 + np.linspace(0, duration, n_meas) + i * duration / n_meas / 3
        if pid == "2":
            t = t[~(((t - t0) > 60) & ((t - t0) < 65)) & ~(((t - t0) > 150) & ((t - t0) < 155))]
        R, p = body(t)
        xyz = np.einsum("kij,j->ki", R, R_BODY[i]) + p + rng.normal(0, 1e-3, (t.size, 3))
        rng_m = np.linalg.norm(xyz - stations[pid], axis=1)
        by_source = {s: source_sigma(s, rng_m)[:, None, None] ** 2 * np.eye(3)
                     for s in NOISE_SOURCES}
        cov = np.sum(list(by_source.values()), axis=0)
        measurements[pid] = PrismTrack(t, xyz, cov, by_source, pid, "world", pid, rng_m)
    tq = t0 + 1.0 + np.arange(n_query) * (duration - 2.0) / n_query
    R, p = body(tq)
    q = np.einsum("kij,nj->kni", R, R_BODY) + p[:, None, :]
    rq = np.linalg.norm(q - np.stack([stations[i] for i in ids])[None], axis=-1)
    by_source_q = {s: source_sigma(s, rq)[..., None, None] ** 2 * np.eye(3)
                   for s in NOISE_SOURCES}
    cov_gp = 0.7 * (by_source_q["instrument"] + by_source_q["tilt"])
    cov_q = cov_gp + sum(by_source_q[s] for s in ("atmosphere", "time_sync", "calibration"))
    ref_cov = ref_sigma ** 2 * np.eye(9)
    est = estimate_poses(q, cov_q, R_BODY, ref_cov, engine="linear", registration="unweighted")
    keep = np.ones(n_query, bool)
    keep[::reject_every] = False
    reasons = np.where(np.arange(n_query) % (2 * reject_every) == 0, "distance", "uncertainty")
    gt = PoseTrajectory(tq[keep], est.t[keep], matrix_to_quat_xyzw(est.R[keep]), est.cov[keep])
    return RunRecord(
        name="synthetic", prism_ids=ids, measurements=measurements, prisms_t=tq,
        prisms_xyz=q, prisms_cov=cov_q, prisms_cov_by_source=by_source_q, prisms_cov_gp=cov_gp,
        groundtruth=gt,
        rejected_t=tq[~keep], rejected_reason=reasons[~keep],
        reference=ReferencePoints(ids, R_BODY.copy(), ref_cov),
        options=RunOptions(seed=seed).updated(engine="linear", samples=200,
                                              registration="unweighted"), stations=stations,
        gcp_xyz=np.array([[10.0, 5.0, 0.0], [50.0, -12.0, 0.5], [120.0, 8.0, 1.0]]),
        gcp_names=("1", "2", "3"), summary={"name": "synthetic"},
    )


def write_run_dir(data: RunRecord, out: Path) -> Path:
    """Write ``data`` in the layout documented in :mod:`rtsgt.io.run_dir`."""
    (out / "prisms").mkdir(parents=True)
    (out / "measurements").mkdir()
    gt = data.groundtruth
    header = (["t", "x", "y", "z", "qx", "qy", "qz", "qw"]
              + [f"cov_{i}{j}" for i in range(6) for j in range(6)])
    write_csv(out / "groundtruth_covariance.csv", header,
              [gt.t, gt.position, gt.quat_xyzw, gt.cov.reshape(len(gt), 36)])
    with (out / "rejected_poses.csv").open("w") as fh:
        fh.write("t,reason\n")
        for t, r in zip(data.rejected_t, data.rejected_reason, strict=True):
            fh.write(f"{float(t)!r},{r}\n")
    cov_names = [f"cov_{c}" for c in COV3_NAMES]
    for i, pid in enumerate(data.prism_ids):
        write_csv(out / "prisms" / f"prism{pid}.csv", ["t", "x", "y", "z"] + cov_names,
                  [data.prisms_t, data.prisms_xyz[:, i], cov3_to_columns(data.prisms_cov[:, i])])
        srcs = list(data.prisms_cov_by_source)
        write_csv(out / "prisms" / f"prism{pid}_sources.csv",
                  ["t"] + [f"gp_{c}" for c in COV3_NAMES]
                  + [f"{s}_{c}" for s in srcs for c in COV3_NAMES],
                  [data.prisms_t, cov3_to_columns(data.prisms_cov_gp[:, i])]
                  + [cov3_to_columns(data.prisms_cov_by_source[s][:, i]) for s in srcs])
        tr = data.measurements[pid]
        srcs = list(tr.cov_by_source)
        write_csv(out / "measurements" / f"prism{pid}.csv",
                  ["t", "x", "y", "z"] + cov_names + ["range_m"]
                  + [f"{s}_{c}" for s in srcs for c in COV3_NAMES],
                  [tr.t, tr.xyz, cov3_to_columns(tr.cov_by_source["instrument"]), tr.range_m]
                  + [cov3_to_columns(tr.cov_by_source[s]) for s in srcs])
    with (out / "reference.csv").open("w") as fh:
        fh.write("name,x,y,z," + ",".join(cov_names) + "\n")
        for i, pid in enumerate(data.prism_ids):
            c = cov3_to_columns(data.reference_cov[3 * i:3 * i + 3, 3 * i:3 * i + 3][None])[0]
            fh.write(",".join([pid] + [repr(float(v)) for v in
                                                  np.r_[data.reference_xyz[i], c]]) + "\n")
    summary = {  # the keys rtsgt.io.run_dir.run_summary writes
        "deployment": data.name,
        "parameters": {"engine": data.options.pose.engine, "samples": data.options.pose.samples,
                       "seed": data.options.seed, "gp_noise": "white"},
        "calibration": {"reference_station": "1", "stations": {
            s: {"translation_m": p.tolist()} for s, p in data.stations.items() if s != "1"}},
        "reference": {"names": list(data.prism_ids), "xyz_m": data.reference_xyz.tolist(),
                      "cov_m2": data.reference_cov.tolist()},
    }
    (out / "summary.json").write_text(json.dumps(summary))
    return out


@pytest.fixture(scope="module")
def run_data() -> RunRecord:
    return make_run_data()


@pytest.fixture(scope="module")
def analysis(run_data):
    return analyze(run_data)


def test_paper_medians_are_the_published_ones():
    """docs/paper-figures.md#per-source-medians (Vaidis et al. 2023)."""
    assert paper_median_mm("instrument") == 2.1
    assert paper_median_mm("instrument", 150, np.inf) == 2.78
    assert [paper_median_mm("calibration", a, b) for a, b in
            ((0, 75), (75, 150), (150, np.inf))] == [0.91, 1.88, 5.49]
    assert paper_median_mm("calibration") == 1.32
    assert paper_median_mm("time_sync") == 0.4
    assert paper_median_mm("atmosphere") == 0.16
    assert paper_median_mm("tilt") == 0.06
    assert paper_median_mm("tilt", 0, 75) is None
    assert set(PAPER_MEDIANS_MM) == set(NOISE_SOURCES)


def test_bins_parsing_and_labels():
    assert parse_bins("0,75,150") == (0.0, 75.0, 150.0)
    assert parse_bins([0, 50]) == (0.0, 50.0)
    assert bin_labels((0, 75, 150)) == ("0-75 m", "75-150 m", "> 150 m")
    for bad in ("0,150,75", "a,b", "", "-5,10", "0,inf"):
        with pytest.raises(InputError):
            parse_bins(bad)


def test_sqrt_frobenius_closed_form(run_data, analysis):
    """Isotropic s^2 I: sqrt(||Sigma||_F) = 3^(1/4) s (mm)."""
    r = analysis.range_m
    for s in NOISE_SOURCES:
        expect = 3 ** 0.25 * source_sigma(s, r) * 1e3
        np.testing.assert_allclose(analysis.norm_mm[s], expect, rtol=1e-12)
    total_sigma = np.sqrt(sum(source_sigma(s, r) ** 2 for s in NOISE_SOURCES))
    np.testing.assert_allclose(analysis.norm_mm[ALL], 3 ** 0.25 * total_sigma * 1e3, rtol=1e-12)
    assert analysis.sources == NOISE_SOURCES + (ALL,)
    assert analysis.n_measurements == sum(len(tr) for tr in run_data.measurements.values())


def test_bin_medians_counts_and_shares(analysis):
    r = analysis.range_m
    edges = [0, 75, 150, np.inf]
    counts = [int(np.sum((r >= a) & (r < b))) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    assert analysis.bin_counts == tuple(counts)
    assert min(counts) > 20  # the synthetic run spans every bin
    np.testing.assert_allclose(analysis.bin_shares, np.array(counts) / r.size)
    assert sum(analysis.bin_shares) == pytest.approx(1.0)
    for s in analysis.sources:
        for k, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
            m = (r >= a) & (r < b)
            assert analysis.bin_median_mm[s][k] == pytest.approx(
                np.median(analysis.norm_mm[s][m]), rel=1e-12)
        assert analysis.median_mm[s] == pytest.approx(np.median(analysis.norm_mm[s]))
    # the calibration source grows with range, as in the paper
    cal = analysis.bin_median_mm["calibration"]
    assert cal[0] < cal[1] < cal[2]


def test_custom_bins(run_data):
    a = analyze(run_data, bins="0,100")
    assert a.bin_labels == ("0-100 m", "> 100 m")
    assert sum(a.bin_counts) == a.n_measurements
    rows = a.table_rows()
    assert rows[0]["bins"][0]["paper_median_mm"] is None  # the paper has no 0-100 m bin


def test_pose_translation_closed_form(run_data, analysis):
    """Three prisms, s^2 I each, exact reference centred at the origin: sqrt(tr) = s."""
    idx = np.searchsorted(run_data.prisms_t, analysis.pose_t)
    for s in ("instrument", "calibration"):
        c = run_data.prisms_cov_by_source[s][idx]
        s_rms = np.sqrt(np.mean(c[..., 0, 0], axis=1))  # isotropic, prisms slightly different
        np.testing.assert_allclose(analysis.translation_mm[s], s_rms * 1e3, rtol=1e-9)


def test_pose_sources_add_up_to_first_order(run_data, analysis):
    """Linear engine: sum over the sources and the reference = pose of the summed inputs."""
    idx = np.searchsorted(run_data.prisms_t, analysis.pose_t)
    q = run_data.prisms_xyz[idx]
    total_q = sum(run_data.prisms_cov_by_source[s][idx] for s in NOISE_SOURCES)
    expect = estimate_poses(q, total_q, run_data.reference_xyz, run_data.reference_cov,
                            engine="linear", registration="unweighted").cov
    got = sum(analysis.pose_cov[s] for s in NOISE_SOURCES + (REFERENCE,))
    np.testing.assert_allclose(got, expect, rtol=1e-9, atol=1e-18)
    # a weighted run: every source through the run's fit (the weights of the total), so the
    # sources still add up, and differ from the unweighted fit's
    weighted = dataclasses.replace(run_data,
                                   options=run_data.options.updated(registration="weighted"))
    w = analyze(weighted)
    fit = {"engine": "linear", "registration": "weighted",
           "weight_cov_q": run_data.prisms_cov[idx], "weight_cov_r": run_data.reference_cov}
    expect_w = estimate_poses(q, total_q, run_data.reference_xyz, run_data.reference_cov,
                              **fit).cov
    np.testing.assert_allclose(sum(w.pose_cov[s] for s in NOISE_SOURCES + (REFERENCE,)),
                               expect_w, rtol=1e-9, atol=1e-18)
    parts_w = sum(w.pose_cov[s] for s in (GP, "atmosphere", "time_sync", "calibration",
                                         REFERENCE))
    np.testing.assert_allclose(parts_w, estimate_poses(q, run_data.prisms_cov[idx],
                                                       run_data.reference_xyz,
                                                       run_data.reference_cov, **fit).cov,
                               rtol=1e-9, atol=1e-18)
    assert not np.allclose(expect_w, expect, rtol=1e-3, atol=0)
    assert analysis.pose_sources == NOISE_SOURCES + (GP, REFERENCE, ALL)
    np.testing.assert_array_equal(analysis.pose_cov[ALL], run_data.groundtruth.cov)
    # the run's total = GP posterior + systematic sources + reference, to first order
    parts = (GP, "atmosphere", "time_sync", "calibration", REFERENCE)
    np.testing.assert_allclose(sum(analysis.pose_cov[s] for s in parts),
                               analysis.pose_cov[ALL], rtol=1e-9, atol=1e-18)


def test_pose_measures(analysis):
    c = analysis.pose_cov[ALL]
    tr, rot = pose_sigmas(c, "sqrt_trace")
    np.testing.assert_allclose(tr, np.sqrt(np.trace(c[:, :3, :3], axis1=1, axis2=2)) * 1e3)
    np.testing.assert_allclose(rot, np.sqrt(np.trace(c[:, 3:, 3:], axis1=1, axis2=2)) * 1e3)
    tr2, rot2 = pose_sigmas(c, "max_std")
    np.testing.assert_allclose(tr2, np.sqrt(np.linalg.eigvalsh(c[:, :3, :3])[:, -1]) * 1e3)
    assert np.all(tr2 <= tr + 1e-12) and np.all(tr2 >= tr / np.sqrt(3) - 1e-12)
    with pytest.raises(InputError):
        pose_sigmas(c, "frobenius")


def test_monte_carlo_engine_agrees_with_linear(run_data, analysis):
    """The per-source poses by the run's Monte Carlo engine match first order within 10 %."""
    mc = analyze(run_data, engine="mc", samples=4000, seed=3)
    assert mc.engine == "mc" and mc.samples == 4000
    for s in ("instrument", "calibration", REFERENCE):
        ratio = mc.translation_mm[s] / analysis.translation_mm[s]
        assert abs(np.median(ratio) - 1) < 0.03, s
        assert np.all(np.abs(ratio - 1) < 0.10), s
    small = analyze(run_data, engine="mc", samples=300, seed=3)
    again = analyze(run_data, engine="mc", samples=300, seed=3)  # same seed, same numbers
    np.testing.assert_array_equal(again.translation_mm["tilt"], small.translation_mm["tilt"])
    other = analyze(run_data, engine="mc", samples=300, seed=4)
    assert not np.array_equal(other.translation_mm["tilt"], small.translation_mm["tilt"])


def test_to_dict_is_json(analysis):
    d = json.loads(json.dumps(analysis.to_dict()))
    inst = next(r for r in d["sources"] if r["source"] == "instrument")
    assert inst["paper_median_mm"] == 2.1
    assert inst["bins"][2]["paper_median_mm"] == 2.78
    assert inst["median_mm"] == pytest.approx(analysis.median_mm["instrument"])
    assert d["pose"]["n_poses"] == analysis.pose_t.size
    assert [r["source"] for r in d["pose"]["sources"]] == list(analysis.pose_sources)
    full = analysis.to_dict(include_arrays=True)
    assert len(full["arrays"]["norm_mm"]["tilt"]) == analysis.n_measurements


def test_directory_round_trip(run_data, analysis, tmp_path):
    """Writing the documented layout and reading it back gives the same analysis."""
    write_run_dir(run_data, tmp_path / "run")
    back = read_run(tmp_path / "run")
    assert back.prism_ids == run_data.prism_ids
    assert back.sources == NOISE_SOURCES
    np.testing.assert_array_equal(back.rejected_reason, run_data.rejected_reason)
    np.testing.assert_allclose(back.stations["2"], run_data.stations["2"])
    np.testing.assert_array_equal(back.stations["1"], np.zeros(3))
    a2 = analyze_dir(tmp_path / "run")
    for s in analysis.sources:
        np.testing.assert_allclose(a2.norm_mm[s], analysis.norm_mm[s], rtol=1e-12)
        assert a2.bin_median_mm[s] == pytest.approx(analysis.bin_median_mm[s], rel=1e-12)
    for s in analysis.pose_sources:
        np.testing.assert_allclose(a2.translation_mm[s], analysis.translation_mm[s], rtol=1e-9)
        np.testing.assert_allclose(a2.rotation_mrad[s], analysis.rotation_mrad[s], rtol=1e-9)


def test_reader_errors_name_the_file(run_data, tmp_path):
    run = write_run_dir(run_data, tmp_path / "run")
    with pytest.raises(InputError, match="run directory not found"):
        read_run(tmp_path / "nope")
    p = run / "prisms" / "prism2.csv"
    lines = p.read_text().splitlines()
    lines[3] = lines[3].replace(",", ",x", 1)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"prism2\.csv:4: not a number"):
        read_run(run)
    (run / "groundtruth_covariance.csv").unlink()
    p.write_text("\n".join(lines[:3]) + "\n")
    with pytest.raises(InputError, match="prism2.csv"):
        read_run(run)


def test_station_positions_from_calibrate_json():
    summary = {"calibration": {"reference_station": 1, "stations": {
        "2": {"matrix": [[1, 0, 0, 4.0], [0, 1, 0, -2.0], [0, 0, 1, 0.5], [0, 0, 0, 1]]}}}}
    st = station_positions_from_summary(summary)
    assert list(st) == ["1", "2"]
    np.testing.assert_array_equal(st["2"], [4.0, -2.0, 0.5])
    assert station_positions_from_summary({}) == {}


# --------------------------------------------------------------------------------------------
# a run of the real pipeline (simulated deployment): in memory and from its directory
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pipeline_run(tmp_path_factory):
    """A 90 s simulated deployment through the pipeline (Monte Carlo engine), written out."""

    from rtsgt.io.deployment import load_deployment
    from rtsgt.io.run_dir import write_run
    from rtsgt.pipeline import run_pipeline
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

    tmp = tmp_path_factory.mktemp("pipeline-run")
    sim = simulate_deployment(SimulationConfig(duration_s=90.0), np.random.default_rng(5))
    data, opts = load_deployment(write_deployment(sim, tmp / "deployment"))
    result = run_pipeline(data, opts.updated(engine="mc", samples=200, seed=5))
    return sim, result, write_run(result, tmp / "run")


def test_nearest_psd_clips_round_off_only():
    rng = np.random.default_rng(4)
    g = rng.normal(size=(50, 3))
    rank1 = g[:, :, None] * g[:, None, :] * 1e-8  # a tilt-like source: rank one
    e = rng.normal(scale=1e-8 * 1e-8, size=rank1.shape)
    noisy = rank1 + e + np.swapaxes(e, 1, 2)  # round-off of relative size 1e-8
    assert np.linalg.eigvalsh(noisy)[:, 0].min() < 0
    with pytest.raises(ValueError, match="positive semi-definite"):
        check_covariance(noisy, 3)  # what the pose engines refused on the real excerpt
    fixed = nearest_psd(noisy)
    check_covariance(fixed, 3, tol=1e-12)
    w = np.linalg.eigvalsh(fixed)
    scale = np.abs(fixed).max(axis=(1, 2))
    assert np.all(w[:, 0] >= -1e-14 * scale)
    np.testing.assert_array_equal(fixed, np.swapaxes(fixed, 1, 2))
    np.testing.assert_allclose(fixed, rank1, atol=1e-15)  # only the round-off is changed
    spd = np.eye(3)[None] * np.array([1e-6, 2e-6])[:, None, None]
    np.testing.assert_array_equal(nearest_psd(spd), spd)  # PSD input is returned as is
    with_nan = np.concatenate([noisy[:2], np.full((1, 3, 3), np.nan)])
    out = nearest_psd(with_nan)
    assert np.isnan(out[2]).all() and np.isfinite(out[:2]).all()


def test_pipeline_run_in_memory_equals_run_directory(pipeline_run):
    """The per-source covariances of a real run (rank-deficient sources included) go through
    the pose engine, and reading the directory gives the analysis of the in-memory run."""
    _, result, run_dir = pipeline_run
    mem = analyze(result, engine="mc")
    disk = analyze_dir(run_dir, engine="mc")
    assert mem.engine == disk.engine == "mc" and mem.samples == 200
    # the default split is the first-order one, and agrees with the Monte Carlo split to its
    # noise (M = 200: about 5 % of a sigma per pose, less for a median over the poses)
    first = analyze(result)
    assert first.engine == "linear" and first.samples is None
    for s in first.pose_sources:
        for a, b in ((first.pose_median_translation_mm, mem.pose_median_translation_mm),
                     (first.pose_median_rotation_mrad, mem.pose_median_rotation_mrad)):
            assert abs(a[s] / b[s] - 1) < 0.1, (s, a[s], b[s])
    assert mem.sources == disk.sources == NOISE_SOURCES + (ALL,)
    assert mem.n_measurements == sum(len(tr) for tr in result.computation.tracks.values())
    for s in mem.sources:
        np.testing.assert_allclose(disk.norm_mm[s], mem.norm_mm[s], rtol=1e-12)
    assert mem.pose_sources == disk.pose_sources
    assert mem.pose_t.size == len(result.groundtruth) > 100
    for s in mem.pose_sources:
        assert np.all(np.isfinite(mem.translation_mm[s])), s
        assert np.all(np.isfinite(disk.translation_mm[s])), s
    # the files hold the upper triangle of each 3x3 (in memory: symmetric to round-off), which
    # can change the Monte Carlo draws of rank-deficient sources; first order is exact
    mem, disk = analyze(result, engine="linear"), analyze_dir(run_dir, engine="linear")
    for s in mem.pose_sources:
        v = mem.translation_mm[s]
        np.testing.assert_allclose(disk.translation_mm[s], v, rtol=1e-9, atol=1e-12 * v.max())
    np.testing.assert_allclose(mem.pose_cov[ALL], result.groundtruth.cov)


def test_run_directory_has_the_gcps_and_stations(pipeline_run):
    sim, result, run_dir = pipeline_run
    data = read_run(run_dir)
    truth = sim.truth
    assert set(data.gcp_names) <= set(truth.gcp_markers) and len(data.gcp_names) >= 4
    idx = [truth.gcp_markers.index(m) for m in data.gcp_names]
    # the shots' mean mapped through the calibration lands within a few mm of the markers
    err = np.linalg.norm(data.gcp_xyz - truth.gcp_world[idx], axis=1)
    assert np.max(err) < 0.02, err
    for sid, T in truth.T_world_station.items():
        np.testing.assert_allclose(data.stations[sid], T.translation, atol=0.01)


def test_removed_measurements_are_written_and_read_back(pipeline_run):
    """measurements/removed.csv: what modules 1 and 2 removed, counts as in the reports."""
    from rtsgt.report.figures import plot_top_view, plot_uncertainty_time

    _, result, run_dir = pipeline_run
    removed = result.removed
    rep = result.computation.filter_reports
    n1 = sum(r.n_removed for k, r in rep.items() if k.startswith("module1"))
    n2 = rep["module2"].n_removed
    assert np.sum(removed.stage == "module1") == n1
    assert np.sum(removed.stage == "module2") == n2 and n1 + n2 > 0
    data = read_run(run_dir)
    np.testing.assert_allclose(data.removed.t, removed.t, atol=1e-9)
    np.testing.assert_allclose(data.removed.xyz, removed.xyz, atol=1e-6)
    np.testing.assert_array_equal(data.removed.stage, removed.stage)
    np.testing.assert_array_equal(data.removed.prism, removed.prism)
    # none of them is among the measurements kept for the prism
    for pid, tr in result.computation.tracks.items():
        assert not np.isin(data.removed.t[data.removed.prism == pid], tr.t).any()
    # removed measurements lie on the robot's path: within a few metres of a kept one
    kept = np.concatenate([tr.xyz for tr in result.computation.tracks.values()])
    d = np.min(np.linalg.norm(data.removed.xyz[:, None] - kept[None], axis=-1), axis=1)
    assert np.median(d) < 2.0
    top, along = plot_top_view(data), plot_uncertainty_time(data)
    for stage in ("module1", "module2"):
        n = int(np.sum(data.removed.stage == stage))
        if n:
            assert top.points[f"removed: {stage}"] == n == along.points[f"removed: {stage}"]
