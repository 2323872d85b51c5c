"""Dynamic self-calibration of the stations from the inter-prism distances (and joint with the
GCPs): exact recovery, the covariance's consistency pooled over noise draws, the Monte Carlo
against the linear covariance, the refusals, and on simulated deployments with known truth.

The synthetic samples here are built from an analytic robot trajectory (a figure of eight with
roll and pitch of the terrain) seen by three stations, with white noise of known covariance:
they test the fit and its covariance without the GPs. The simulated deployments test the whole
chain (the GPs' weights included); ``benchmarks/calibration_dynamic.py`` pools 60 of them.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from rtsgt.calibration import calibrate
from rtsgt.calibration.dynamic import DistanceSamples, calibrate_dynamic
from rtsgt.calibration.shots import curvature_tilt
from rtsgt.errors import GeometryError, InputError, RtsgtWarning
from rtsgt.geometry.so3 import exp_so3
from rtsgt.geometry.transform import perturbation
from rtsgt.measurement.polar import cartesian_to_polar
from rtsgt.types import GcpShots

#: Prisms on the robot (robot frame, m): the simulator's Warthog-like three.
PRISMS = np.array([(0.40, 0.30, 0.80), (0.40, -0.42, 0.64), (-0.45, 0.05, 0.95)])
#: Station 2 and 3: yaw (rad), translation (m), tilt (rad) when not levelled.
SETUP = {"2": (2.0, (35.0, -20.0, 0.7), (0.002, -0.004)),
         "3": (-1.1, (-25.0, 30.0, -0.4), (-0.003, 0.001))}
#: Clock offsets of stations 1, 2, 3 (t_true - t_stamped), s.
CLOCKS = (0.4e-3, 1.9e-3, -2.1e-3)
STATIONS = ("1", "2", "3")


def robot(t, *, flat=False, straight=False):
    """Robot pose (R_world_robot, centre) at times ``t``: a figure of eight of 40 x 20 m, the
    heading along the path, roll and pitch of +-3 degrees and 0.5 m of relief (``flat``: none;
    ``straight``: a straight line, no rotation)."""
    if straight:
        return (np.broadcast_to(np.eye(3), t.shape + (3, 3)),
                np.stack([1.0 * t, 0.3 * t, 0.0 * t], -1))
    w = 2 * np.pi / 120.0
    c = np.stack([20 * np.sin(w * t), 10 * np.sin(2 * w * t), np.zeros_like(t)], -1)
    yaw = np.arctan2(10 * 2 * w * np.cos(2 * w * t), 20 * w * np.cos(w * t))
    tilt = 0.0 if flat else np.radians(3.0)
    if not flat:
        c[:, 2] = 0.5 * np.sin(0.05 * t)
    zero = np.zeros_like(t)
    R = (exp_so3(np.stack([tilt * np.sin(0.31 * t), tilt * np.cos(0.17 * t), zero], -1))
         @ exp_so3(np.stack([zero, zero, yaw], -1)))
    return R, c


def stations(levelled=True):
    """True ``T_world_station``: levelled (the Earth's curvature only) or tilted a little."""
    out = {"1": (np.eye(3), np.zeros(3))}
    for s, (yaw, t, tilt) in SETUP.items():
        t = np.array(t)
        om = curvature_tilt(t) if levelled else np.array([*tilt, 0.0])
        out[s] = (exp_so3(om) @ exp_so3(np.array([0.0, 0.0, yaw])), t)
    return out


def synthetic(rng, *, K=120, sigma=1e-3, levelled=True, survey_sigma=0.0, scale_sigma=0.0,
              noise=True, flat=False, straight=False):
    """DistanceSamples of the robot seen by the stations every second, with white noise of
    ``sigma`` per axis (the windows' covariance says so), a common scale error of
    ``scale_sigma``, survey errors of ``survey_sigma`` per distance; and the truth."""
    T = stations(levelled)
    t = 10.0 + np.arange(K, dtype=float)
    xyz, vel = np.empty((K, 3, 3)), np.empty((K, 3, 3))
    for i, s in enumerate(STATIONS):
        def q(tt, i=i):
            R, c = robot(tt, flat=flat, straight=straight)
            return np.einsum("kij,j->ki", R, PRISMS[i]) + c
        tt = t + CLOCKS[i] - CLOCKS[0]  # a stamp of station s, in the reference's time
        R_s, t_s = T[s]
        xyz[:, i] = (q(tt) - t_s) @ R_s
        vel[:, i] = ((q(tt + 1e-4) - q(tt - 1e-4)) / 2e-4) @ R_s
    pairs = ((0, 1), (0, 2), (1, 2))
    d = np.array([np.linalg.norm(PRISMS[i] - PRISMS[j]) for i, j in pairs])
    if noise:
        xyz = xyz * (1.0 + scale_sigma * rng.standard_normal()) \
            + sigma * rng.standard_normal(xyz.shape)
        d = d + survey_sigma * rng.standard_normal(3)
    windows, covs = [], []
    for a in range(0, K, 30):
        idx = np.arange(a, min(K, a + 30))
        G = np.zeros((3, idx.size, idx.size, 3, 3))
        G[:, np.arange(idx.size), np.arange(idx.size)] = sigma ** 2 * np.eye(3)
        windows.append(idx)
        covs.append(G)
    smp = DistanceSamples(t, STATIONS, STATIONS, xyz, vel, tuple(windows), tuple(covs), pairs,
                          d, survey_sigma ** 2 * np.eye(3), scale_sigma ** 2)
    return smp, T


def errors(result, T):
    """Stacked left perturbations of stations 2, 3 (estimate against truth) and the errors of
    their relative clock offsets."""
    e = [perturbation(*T[s], result.transforms[s].rotation, result.transforms[s].translation)
         for s in ("2", "3")]
    clk = [result.dynamic.clock_offset_s[s] - (CLOCKS[k] - CLOCKS[0])
           for k, s in ((1, "2"), (2, "3"))]
    return np.concatenate(e + [clk])


@pytest.mark.parametrize("model", ["6dof", "4dof"])
def test_noise_free_distances_recover_the_stations_and_the_clocks(model):
    smp, T = synthetic(np.random.default_rng(0), noise=False)
    r = calibrate_dynamic(smp, model=model, n_samples=10, rng=np.random.default_rng(0))
    e = errors(r, T)
    # exact but for the clock's first-order model (0.5 a delta^2: about 1e-6 m)
    assert np.max(np.abs(e[:12])) < 1e-5, e
    assert np.max(np.abs(e[12:])) < 1e-6, e
    assert r.method == "dynamic" and r.model == model and r.dynamic.rejected == 0
    assert r.transforms["1"].covariance.sum() == 0.0
    assert r.transforms["2"].samples_rotation.shape == (10, 3, 3)


def test_tilted_stations_under_the_six_dof_model():
    """Stations off level by a few milliradians (what a bubble gives without a compensator):
    the levelled start still leads the 6-DOF fit to them."""
    smp, T = synthetic(np.random.default_rng(0), noise=False, levelled=False)
    r = calibrate_dynamic(smp, model="6dof", n_samples=10, rng=np.random.default_rng(0))
    assert np.max(np.abs(errors(r, T)[:12])) < 1e-5


@pytest.mark.slow
def test_linear_covariance_is_consistent_pooled_over_noise_draws():
    """NEES / dof of the stations' poses and clocks (14 dof) pooled over 60 draws of the
    noise, the survey and the scale (840 dof: +-0.05 at one sigma), so 1.25 fails."""
    nees, factors = [], []
    for k in range(60):
        smp, T = synthetic(np.random.default_rng(k), survey_sigma=0.7e-3, scale_sigma=2e-6)
        r = calibrate_dynamic(smp, model="6dof", n_samples=10, rng=np.random.default_rng(k))
        e = errors(r, T)
        nees.append(e @ np.linalg.solve(r.dynamic.covariance, e))
        factors.append(r.dynamic.variance_factor)
    assert 0.85 < np.mean(nees) / 14 < 1.15, np.mean(nees) / 14
    # the fit check's variance factor is 1 on average (Satterthwaite's dof: about 340 each)
    assert abs(np.mean(factors) - 1.0) < 0.03, np.mean(factors)


@pytest.mark.parametrize("model", ["6dof", "4dof"])
def test_monte_carlo_and_linear_covariances_agree(model):
    smp, _ = synthetic(np.random.default_rng(3), survey_sigma=0.7e-3, scale_sigma=2e-6)
    lin = calibrate_dynamic(smp, model=model, n_samples=2000, rng=np.random.default_rng(1))
    mc = calibrate_dynamic(smp, model=model, engine="mc", n_samples=2000,
                           rng=np.random.default_rng(1))
    idx = [0, 1, 2, 3, 4, 5] if model == "6dof" else [0, 1, 2, 5]
    for s in ("2", "3"):
        a = np.sqrt(np.diag(lin.transforms[s].covariance))[idx]
        b = np.sqrt(np.diag(mc.transforms[s].covariance))[idx]
        np.testing.assert_allclose(b / a, 1.0, atol=0.08)  # MC error: 1.6 % per sigma
        # the samples are those of the covariance (the prism Monte Carlo uses them)
        xi = perturbation(lin.transforms[s].rotation, lin.transforms[s].translation,
                          lin.transforms[s].samples_rotation,
                          lin.transforms[s].samples_translation)
        np.testing.assert_allclose(np.std(xi, axis=0)[idx], a, rtol=0.08)
    for s in ("2", "3"):
        assert mc.dynamic.clock_sigma_s[s] == pytest.approx(lin.dynamic.clock_sigma_s[s],
                                                            rel=0.08)


def test_straight_line_is_refused():
    smp, _ = synthetic(np.random.default_rng(0), straight=True)
    with pytest.raises(GeometryError, match="does not determine"):
        calibrate_dynamic(smp, n_samples=10, rng=np.random.default_rng(0))


@pytest.mark.parametrize("model", ["6dof", "4dof"])
def test_flat_ground_leaves_the_heights_ambiguous(model):
    """Driving on a plane, a prism above another and one below it give the same distances:
    the fit says so instead of picking one."""
    smp, _ = synthetic(np.random.default_rng(0), flat=True)
    with pytest.raises(GeometryError, match="heights of the stations are ambiguous"):
        calibrate_dynamic(smp, model=model, n_samples=10, rng=np.random.default_rng(0))


def test_samples_beyond_the_gate_are_left_out():
    smp, T = synthetic(np.random.default_rng(0), noise=False)
    xyz = smp.xyz.copy()
    xyz[40:43, 1] += 0.5  # station 2 on another prism for 3 s
    bad = DistanceSamples(smp.t, smp.prisms, smp.stations, xyz, smp.velocity, smp.windows,
                          smp.window_cov, smp.pairs, smp.reference_distance,
                          smp.reference_distance_cov)
    r = calibrate_dynamic(bad, n_samples=10, rng=np.random.default_rng(0), gate_m=0.1)
    assert r.dynamic.rejected == 3 and r.dynamic.samples == 117
    assert np.max(np.abs(errors(r, T)[:12])) < 1e-5


def gcp_shots(T, rng, sigma=0.0):
    """Every station shoots ten markers (noise-free, or with ``sigma`` per axis)."""
    markers = np.array([[4.0, 3.0, -0.6], [-18.0, 7.0, 0.9], [25.0, 20.0, 1.8],
                        [40.0, -15.0, 0.1], [-10.0, -30.0, -1.3], [6.0, 50.0, 2.6],
                        [-45.0, -28.0, -0.2], [60.0, 25.0, 2.2], [-30.0, 35.0, 3.5],
                        [15.0, -42.0, -2.0]])
    hz, v, d, st, mk = [], [], [], [], []
    for s in STATIONS:
        R, t = T[s]
        p = (markers - t) @ R + sigma * rng.standard_normal(markers.shape)
        h, z, r = cartesian_to_polar(p)
        hz.append(h)
        v.append(z)
        d.append(r)
        st += [s] * len(markers)
        mk += [str(i + 1) for i in range(len(markers))]
    return GcpShots(st, mk, np.concatenate(hz), np.concatenate(v), np.concatenate(d),
                    additive_constant=0.0)


@pytest.mark.parametrize("model", ["6dof", "4dof"])
def test_joint_calibration_is_exact_without_noise_and_sharper_than_the_gcps(model):
    rng = np.random.default_rng(0)
    smp, T = synthetic(rng, noise=False)
    shots = gcp_shots(T, rng)
    gcp = calibrate(shots, samples=2000, rng=np.random.default_rng(1), model=model)
    joint = calibrate_dynamic(smp, gcp=shots, gcp_calibration=calibrate(shots, samples=0,
                                                                        model=model),
                              model=model, n_samples=10, rng=np.random.default_rng(0))
    assert joint.method == "joint" and joint.dynamic.method == "joint"
    assert np.max(np.abs(errors(joint, T)[:12])) < 1e-5
    assert len(joint.residuals) == 30 and joint.fit_checks  # the GCP fit's checks are kept
    for s in ("2", "3"):
        tr_joint = np.trace(joint.transforms[s].covariance[:3, :3])
        tr_gcp = np.trace(gcp.transforms[s].covariance[:3, :3])
        assert tr_joint < 0.8 * tr_gcp, (s, tr_joint, tr_gcp)


def test_bad_arguments_are_refused():
    smp, _ = synthetic(np.random.default_rng(0), noise=False, K=20)
    with pytest.raises(InputError, match="calibration model"):
        calibrate_dynamic(smp, model="5dof")
    with pytest.raises(InputError, match="engine"):
        calibrate_dynamic(smp, engine="ut")
    with pytest.raises(InputError, match="n_samples"):
        calibrate_dynamic(smp, n_samples=1)
    with pytest.raises(InputError, match="GCP calibration"):
        calibrate_dynamic(smp, gcp=gcp_shots(stations(), np.random.default_rng(0)))
    with pytest.raises(InputError, match="nothing to calibrate"):
        calibrate_dynamic(None)
    no_ref = DistanceSamples(smp.t, smp.prisms, ("4", "2", "3"), smp.xyz, smp.velocity,
                             smp.windows, smp.window_cov, smp.pairs, smp.reference_distance,
                             smp.reference_distance_cov)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="reference station 1 to track"):
            calibrate_dynamic(no_ref)


# ------------------------------------------------------------------ pipeline, options, CLI


def test_the_method_is_an_option_with_its_choices():
    from rtsgt.options import CalibrationOptions, RunOptions

    assert CalibrationOptions().method == "gcp"
    assert RunOptions().updated(method="joint").calibration.method == "joint"
    with pytest.raises(InputError, match="calibration method 'gcp' or 'dynamic' or 'joint'"):
        CalibrationOptions(method="motion")


def test_the_toml_sets_the_method(tmp_path):
    from rtsgt.errors import ConfigError
    from rtsgt.io.config import load_config

    files = ("p1.csv", "p2.csv", "p3.csv", "gcp.txt", "survey.csv")
    for name in files:
        (tmp_path / name).write_text("x\n")
    stations = "".join(f'[[stations]]\nid = "{k}"\nprism = "{k}"\nfile = "p{k}.csv"\n'
                       for k in (1, 2, 3))
    base = (f'[deployment]\nreference_station = "1"\n{stations}[gcp]\nfile = "gcp.txt"\n'
            '[reference]\nfile = "survey.csv"\nprisms = { "1" = 1, "2" = 2, "3" = 3 }\n')
    cfg = tmp_path / "deployment.toml"
    cfg.write_text(base)
    assert load_config(cfg).options.calibration.method == "gcp"
    for method in ("dynamic", "joint"):
        cfg.write_text(base + f'[calibration]\nmethod = "{method}"\nmodel = "4dof"\n')
        c = load_config(cfg).options.calibration
        assert (c.method, c.model) == (method, "4dof")
    cfg.write_text(base + '[calibration]\nmethod = "motion"\n')
    with pytest.raises(ConfigError, match=r"\[calibration\] method = 'motion'"):
        load_config(cfg)


def test_a_joint_run_records_its_calibration(tmp_path, capsys):
    """The pipeline with the joint calibration: its self-check, the coupling of the stations
    from its samples, summary.json's method and a run read back with it."""
    from rtsgt.io.deployment import load_deployment
    from rtsgt.io.run_dir import read_run, write_run
    from rtsgt.pipeline import run_pipeline
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

    sim = simulate_deployment(SimulationConfig(duration_s=60.0), np.random.default_rng(21))
    data, opts = load_deployment(write_deployment(sim, tmp_path / "dep"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_pipeline(data, opts.updated(method="joint", engine="linear", samples=50,
                                              seed=3))
    check = rec.self_checks["dynamic_calibration"]
    assert check["method"] == "joint" and check["engine"] == "linear"
    assert set(check["clock_offset_ms"]) == {"2", "3"} and "gcp_agreement" not in check
    calib = rec.computation.calibration
    assert calib.method == "joint" and calib.transforms["2"].samples_rotation.shape[0] == 50
    assert ("2", "3") in rec.coupling.cross  # the stations' errors, jointly
    for s in ("2", "3"):  # the truth, within a few sigma
        e = perturbation(sim.truth.T_world_station[s].rotation,
                         sim.truth.T_world_station[s].translation,
                         calib.transforms[s].rotation, calib.transforms[s].translation)
        assert e @ np.linalg.solve(calib.transforms[s].covariance, e) < 40.0
    out = write_run(rec, tmp_path / "run")
    import json
    summary = json.loads((out / "summary.json").read_text())
    assert summary["parameters"]["calibration_method"] == "joint"
    assert summary["calibration"]["method"] == "joint"
    assert summary["self_checks"]["dynamic_calibration"]["method"] == "joint"
    assert read_run(out).options.calibration.method == "joint"
    # the run's table and the report show it
    from rtsgt.cli.common import print_run_summary
    from rtsgt.report.html import _self_checks_html

    html = _self_checks_html(summary["self_checks"])
    assert "check-dynamic-calibration" in html and "check-dynamic-clocks" in html
    print_run_summary(rec, out)
    shown = capsys.readouterr().out
    assert "calibration method" in shown and "clock offset, station 2" in shown


def test_calibrate_command_on_the_excerpt():
    """``rtsgt calibrate`` with a deployment's TOML: the joint calibration (clock offsets of a
    few milliseconds), and the dynamic one refused with its reason (86 s of track do not
    determine the stations to a centimetre)."""
    import json

    from typer.testing import CliRunner

    from _paths import EXAMPLE_TOML
    from rtsgt.cli.main import app

    runner = CliRunner()
    res = runner.invoke(app, ["calibrate", str(EXAMPLE_TOML), "--method", "joint",
                              "--samples", "50", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["method"] == "joint" and out["dynamic"]["method"] == "joint"
    assert all(abs(v) < 5.0 for v in out["dynamic"]["clock_offset_ms"].values())
    # the GCPs' transforms (test_calibration: SOURCE.md's figures) within a few millimetres
    np.testing.assert_allclose(out["stations"]["2"]["translation_m"], [-0.659, -1.301, 0.286],
                               atol=0.005)
    res = runner.invoke(app, ["calibrate", "--dynamic", str(EXAMPLE_TOML), "--samples", "50"])
    assert res.exit_code == 1
    assert "does not determine station" in res.output and "drive a path" in res.output


def test_calibrate_command_refuses_what_it_cannot_do():
    from typer.testing import CliRunner

    from _paths import EXAMPLE_TOML, EXCERPT
    from rtsgt.cli.main import app

    runner = CliRunner()
    res = runner.invoke(app, ["calibrate", str(EXCERPT / "GCP.txt"), "--dynamic"])
    assert res.exit_code == 2 and "deployment's TOML" in res.output
    res = runner.invoke(app, ["calibrate", str(EXAMPLE_TOML), "--dynamic", "--method", "joint"])
    assert res.exit_code == 2 and "give one" in res.output
    res = runner.invoke(app, ["calibrate", str(EXAMPLE_TOML), "--method", "motion"])
    assert res.exit_code == 2 and "gcp or dynamic or joint" in res.output


@pytest.mark.slow
def test_simulated_deployments_the_whole_chain(tmp_path):
    """Six simulated deployments of 400 s whose clocks are 3 ms off (+-1 ms, signs at random),
    through the pipeline's own inputs (the tracks in the stations' frames, their GPs): the
    dynamic and the joint calibrations are near the truth in their own sigma, the clock offsets
    are found, and the joint sigma is below the GCP calibration's for every station. The
    pooled NEES of 6 deployments (72 dof) is only a coarse check (+-0.17 at one sigma);
    benchmarks/calibration_dynamic.py pools 60."""
    from rtsgt.filtering import module1
    from rtsgt.io.deployment import load_deployment
    from rtsgt.noise import NoiseModel
    from rtsgt.pipeline import calibration_samples
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

    nees, dof, clock_z, refused = {"dynamic": 0.0, "joint": 0.0}, {"dynamic": 0, "joint": 0}, [], 0
    for seed in range(9100, 9106):
        cfg = SimulationConfig(duration_s=400.0, time_sync_mean_s=3e-3, time_sync_std_s=1e-3)
        sim = simulate_deployment(cfg, np.random.default_rng(seed))
        data, opts = load_deployment(write_deployment(sim, tmp_path / f"dep{seed}"))
        truth = sim.truth
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            filtered = [module1(o, opts.filter)[0] for o in data.observations]
            smp = calibration_samples(data, filtered, NoiseModel(instrument=data.instrument),
                                      opts)
            gcp = calibrate(data.gcp, samples=300, rng=np.random.default_rng(seed))
            results = {"joint": calibrate_dynamic(
                smp, gcp=data.gcp, gcp_calibration=calibrate(data.gcp, samples=0),
                n_samples=10, rng=np.random.default_rng(seed))}
            try:
                results["dynamic"] = calibrate_dynamic(smp, n_samples=10,
                                                       rng=np.random.default_rng(seed))
            except GeometryError:
                refused += 1
        for name, r in results.items():
            e = np.concatenate([perturbation(truth.T_world_station[s].rotation,
                                             truth.T_world_station[s].translation,
                                             r.transforms[s].rotation,
                                             r.transforms[s].translation) for s in ("2", "3")])
            clk = np.array([r.dynamic.clock_offset_s[s] - (truth.clock_offset_s[s]
                                                         - truth.clock_offset_s["1"])
                            for s in ("2", "3")])
            x = np.concatenate([e, clk])
            nees[name] += float(x @ np.linalg.solve(r.dynamic.covariance, x))
            dof[name] += 14
            clock_z += list(clk / np.array([r.dynamic.clock_sigma_s[s] for s in ("2", "3")]))
        for s in ("2", "3"):
            assert (np.trace(results["joint"].transforms[s].covariance[:3, :3])
                    < np.trace(gcp.transforms[s].covariance[:3, :3])), (seed, s)
    assert refused <= 2 and dof["dynamic"] >= 4 * 14
    for name in ("dynamic", "joint"):
        assert 0.5 < nees[name] / dof[name] < 1.6, (name, nees[name] / dof[name])
    assert np.mean(np.square(clock_z)) < 2.0, np.round(clock_z, 2)


def test_a_station_the_gcps_place_elsewhere_is_named_with_its_axis_and_size():
    """Issue 23: where the GCP and the dynamic calibration disagree beyond their sigmas, the
    run names the station, the axis and the size (a GCP fit 16 mm higher for station 2)."""
    from dataclasses import replace

    from rtsgt.checks.calibration import dynamic_calibration_check

    rng = np.random.default_rng(4)
    smp, T = synthetic(rng)
    dyn = calibrate_dynamic(smp, model="6dof", n_samples=10, rng=np.random.default_rng(0))
    up = dyn.transforms["2"]
    moved = replace(up, translation=np.asarray(up.translation) + [0.0, 0.0, 0.016])
    gcp = replace(dyn, transforms={**dyn.transforms, "2": moved}, dynamic=None)
    with pytest.warns(RtsgtWarning, match=r"station 2: .* largest along z: the dynamic -16\.0 mm from the GCPs'"):
        check = dynamic_calibration_check(dyn, gcp)
    assert check["gcp_agreement"]["2"]["verdict"] == "disagree"
    assert check["gcp_agreement"]["3"]["verdict"] == "agree"
