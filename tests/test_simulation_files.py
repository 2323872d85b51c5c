"""Files of a simulated deployment (rtsgt.simulation.files) and the `rtsgt simulate` command."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from _paths import EXCERPT as REAL
from rtsgt.errors import InputError
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.files import format_dms

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    sim = simulate_deployment(SimulationConfig(duration_s=90.0), 7)
    out = tmp_path_factory.mktemp("sim") / "deployment"
    toml = write_deployment(sim, out)
    return sim, toml


def _dms(tokens):
    d, m, s = (float(x) for x in tokens)
    return math.radians(d + m / 60.0 + s / 3600.0)


def test_layout(written):
    sim, toml = written
    out = toml.parent
    assert toml.name == "deployment.toml"
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["prism1.csv", "prism2.csv", "prism3.csv", "GCP.txt",
                            "calibration_raw.csv", "weather.csv", "truth.tum",
                            "truth_prisms.csv", "truth.json", "deployment.toml",
                            ".rtsgt-output.json"])
    # no temporary directory left next to it
    assert [p.name for p in out.parent.iterdir()] == [out.name]


def test_prism_files_rts_project_format(written):
    sim, toml = written
    for obs in sim.observations:
        path = toml.parent / f"prism{obs.prism}.csv"
        first = path.read_text().splitlines()[0]
        assert len(first.split(" ")) == 4  # no header, space separated
        a = np.loadtxt(path)
        # t d V Hz, full precision: bit-for-bit equal
        np.testing.assert_array_equal(a[:, 0], obs.t)
        np.testing.assert_array_equal(a[:, 1], obs.d)
        np.testing.assert_array_equal(a[:, 2], obs.v)
        np.testing.assert_array_equal(a[:, 3], obs.hz)
        # like the real files: zenith near pi/2, raw distance without the +0.01 m
        assert np.all((a[:, 2] > 1.2) & (a[:, 2] < 1.9))
        ot = sim.truth.observations[obs.station]
        true_d = np.linalg.norm(
            ot.xyz_world - sim.truth.T_world_station[obs.station].translation, axis=1)
        assert abs(np.median(true_d - a[:, 1]) - 0.01) < 0.002


def test_real_prism_file_looks_alike(written):
    real = np.loadtxt(REAL / "prism1.csv")
    sim = np.loadtxt(written[1].parent / "prism1.csv")
    assert real.shape[1] == sim.shape[1] == 4
    for a in (real, sim):
        assert 1.6e9 < a[0, 0] < 1.8e9
        assert abs(np.median(np.diff(a[:, 0])) - 0.4) < 0.01


def test_gcp_file(written):
    sim, toml = written
    lines = (toml.parent / "GCP.txt").read_text().splitlines()
    assert lines[0] == ("theodolite_number , marker_number , status , elevation , azimuth , "
                        "distance , sec , nsec")
    rows = [ln.split(" , ") for ln in lines[1:]]
    assert all(len(r) == 8 for r in rows)
    g = sim.gcp
    assert [r[0] for r in rows] == list(g.station)
    assert [r[1] for r in rows] == list(g.marker)
    np.testing.assert_array_equal([float(r[3]) for r in rows], g.v)  # elevation = zenith
    np.testing.assert_array_equal([float(r[4]) for r in rows], g.hz)
    np.testing.assert_array_equal([float(r[5]) for r in rows], g.d)
    nsec_text = [r[7] for r in rows]
    assert all(s == str(int(s)) for s in nsec_text)  # never zero-padded
    t = np.array([int(r[6]) + int(r[7]) * 1e-9 for r in rows])
    np.testing.assert_array_equal(t, g.t)


def test_survey_file_dms(written):
    sim, toml = written
    lines = (toml.parent / "calibration_raw.csv").read_text().splitlines()
    sv = sim.survey
    assert len(lines) == len(sv.names) == 6
    for i, ln in enumerate(lines):
        f = ln.split(" ")
        assert len(f) == 15 and f[14] == "0"
        assert abs(_dms(f[0:3]) - sv.hz[i]) < 1e-15
        assert abs(_dms(f[3:6]) - sv.sigma_hz[i]) < 1e-15
        assert abs(_dms(f[6:9]) - sv.v[i]) < 1e-15
        assert abs(_dms(f[9:12]) - sv.sigma_v[i]) < 1e-15
        assert float(f[12]) == sv.d[i] and float(f[13]) == sv.sigma_d[i]
        assert 0 <= int(f[1]) < 60 and 0 <= float(f[2]) < 60


def test_format_dms():
    assert format_dms(0.0) == "00 00 00.0000000000"
    assert format_dms(math.radians(88 + 29 / 60 + 47 / 3600)) == "88 29 47.0000000000"
    assert format_dms(math.radians(4.769 / 3600), pad_degrees=False) == "0 00 04.7690000000"
    # just below a full minute: never 60 seconds
    assert format_dms(math.radians(10 + (60 - 1e-12) / 3600)) == "10 01 00.0000000000"
    assert format_dms(math.radians(10 + (60 - 1e-6) / 3600)) == "10 00 59.9999990000"
    with pytest.raises(ValueError):
        format_dms(-1.0)


def test_survey_matches_the_real_layout(written):
    real = (REAL / "calibration_raw.csv").read_text().split("\n")[0].split()
    sim = (written[1].parent / "calibration_raw.csv").read_text().split("\n")[0].split()
    assert len(real) == len(sim) == 15
    # angles with two-digit degrees, sigmas with one-digit degrees, as in the real file
    assert len(real[6]) == len(sim[6]) == 2 and len(real[3]) == len(sim[3]) == 1
    assert len(sim[0]) in (2, 3)
    # the robot ~10 m from the survey station, in front of it (Hz near 0), near horizontal
    for line in (written[1].parent / "calibration_raw.csv").read_text().splitlines():
        f = line.split()
        assert 9.0 < float(f[12]) < 12.5
        assert int(f[0]) < 10 or int(f[0]) > 350
        assert 85 <= int(f[6]) <= 95


def test_weather_file(written):
    sim, toml = written
    text = (toml.parent / "weather.csv").read_text().splitlines()
    assert text[0] == "t_s,temperature_c,pressure_hpa,humidity_pct"
    a = np.loadtxt(toml.parent / "weather.csv", delimiter=",", skiprows=1)
    w = sim.weather_reported
    np.testing.assert_array_equal(a, np.column_stack([w.t, w.temperature_c, w.pressure_hpa,
                                                      w.humidity_pct]))
    assert np.all(np.diff(a[:, 0]) == 3600.0)
    assert a[0, 0] < sim.gcp.t.min() and a[-1, 0] > sim.observations[0].t.max()


def test_truth_tum_and_prisms(written):
    sim, toml = written
    out = toml.parent
    lines = (out / "truth.tum").read_text().splitlines()
    assert lines[0] == "# t[s] x[m] y[m] z[m] qx qy qz qw"
    a = np.loadtxt(out / "truth.tum", comments="#")
    assert a.shape == (9001, 8)
    np.testing.assert_allclose(np.diff(a[:, 0]), 0.01, atol=1e-6)
    # truth.tum is T_world_robot, the frame of the deployment's ground truth
    p_robot, q_robot = sim.truth_at(a[:, 0])
    np.testing.assert_allclose(a[:, 1:4], p_robot, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(a[:, 4:] * q_robot, axis=1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(a[:, 4:], axis=1), 1.0, atol=1e-12)
    evo_fi = pytest.importorskip("evo.tools.file_interface")
    traj = evo_fi.read_tum_trajectory_file(str(out / "truth.tum"))
    np.testing.assert_array_equal(traj.positions_xyz, a[:, 1:4])
    np.testing.assert_allclose(traj.orientations_quat_wxyz, a[:, [7, 4, 5, 6]])
    # prism tracks: t, prism, x, y, z
    assert (out / "truth_prisms.csv").read_text().split("\n")[0] == "t_s,prism,x_m,y_m,z_m"
    p = np.loadtxt(out / "truth_prisms.csv", delimiter=",", skiprows=1)
    assert p.shape == (9001 * 3, 5)
    np.testing.assert_array_equal(p[:, 1], np.tile([1, 2, 3], 9001))
    np.testing.assert_array_equal(p[:, 2:].reshape(9001, 3, 3), sim.truth.prisms_world)


def test_truth_json(written):
    sim, toml = written
    doc = json.loads((toml.parent / "truth.json").read_text())
    assert doc["seed"] == 7
    assert doc["name"] == "sim-seed-7"
    assert doc["additive_constant_m"] == 0.01
    for sid, T in sim.truth.T_world_station.items():
        st = doc["stations"][sid]
        np.testing.assert_array_equal(np.array(st["T_world_station"]), T.as_matrix())
        assert st["clock_offset_s"] == sim.truth.clock_offset_s[sid]
        assert st["prism"] == sid
    ref = np.array([doc["reference_prisms_body_m"][k] for k in ("1", "2", "3")])
    np.testing.assert_array_equal(ref, sim.truth.reference_body)
    assert doc["config"]["duration_s"] == 90.0
    assert doc["config"]["instrument"]["name"] == "trimble-s7"


def test_deployment_toml_schema(written):
    sim, toml = written
    doc = tomllib.loads(toml.read_text())
    assert doc["deployment"] == {"name": "sim-seed-7", "reference_station": "1"}
    assert doc["instrument"] == {"profile": "trimble-s7"}
    assert doc["stations"] == [
        {"id": s, "prism": s, "file": f"prism{s}.csv", "format": "rts-project",
         "additive_constant_m": 0.01} for s in ("1", "2", "3")
    ]
    assert doc["gcp"] == {"file": "GCP.txt", "format": "rts-project", "additive_constant_m": 0.01}
    assert doc["weather"] == {"file": "weather.csv", "format": "csv"}
    ref = dict(doc["reference"])
    T_survey_body = np.array(ref.pop("T_survey_body"))
    pivot = np.array(ref.pop("rocking_pivot"))  # the robot's origin, in the survey frame
    np.testing.assert_array_equal(pivot, sim.truth.T_body_robot.translation)
    assert ref == {"file": "calibration_raw.csv", "format": "survey-dms",
                   "prisms": {"1": 1, "2": 2, "3": 3}, "body_frame": "transform"}
    np.testing.assert_array_equal(T_survey_body, sim.truth.T_body_robot.as_matrix())
    assert doc["noise"] == {
        "sources": ["instrument", "tilt", "atmosphere", "time_sync", "calibration"],
        "time_sync_mean_s": 1.157e-3, "time_sync_std_s": 0.815e-3,
    }
    filt = doc["filter"]
    assert (filt["tau_s_s"], filt["tau_l_s"]) == (3.0, 2.0)
    # the rate gates bound the true motion seen by every station: module 1 keeps it all
    for obs in sim.observations:
        dt = np.diff(obs.t)
        rate_hz = np.degrees(np.abs(np.diff(np.unwrap(obs.hz)))) / dt
        rate_v = np.degrees(np.abs(np.diff(obs.v))) / dt
        rate_d = np.abs(np.diff(obs.d)) / dt
        short = dt < 1.0
        assert np.all(rate_hz[short] < filt["tau_a_deg_s"])
        assert np.all(rate_v[short] < filt["tau_e_deg_s"])
        assert np.all(rate_d[short] < filt["tau_r_m_s"])
    assert doc["interpolation"] == {"rate_hz": 5.0, "qc": "loo", "max_gap_s": 3.0}
    assert doc["pose"] == {"engine": "mc", "samples": 1000, "distance_gate_m": 0.10,
                           "uncertainty_gate_m": 0.20}
    config = pytest.importorskip("rtsgt.io.config")
    cfg = config.load_config(toml)
    assert [s.file.name for s in cfg.stations] == ["prism1.csv", "prism2.csv", "prism3.csv"]
    assert cfg.reference.prisms == {"1": 1, "2": 2, "3": 3}
    # the pivot read back in the body (robot) frame: its origin
    reference = pytest.importorskip("rtsgt.io.deployment").read_reference(cfg)
    np.testing.assert_allclose(reference.pivot, np.zeros(3), atol=1e-12)


def test_round_trip_with_the_readers(written):
    rts = pytest.importorskip("rtsgt.io.rts_project")
    if not hasattr(rts, "read_prism_file") or not hasattr(rts, "read_gcp_rts_project"):
        pytest.skip("rtsgt.io.rts_project readers not available")
    sim, toml = written
    out = toml.parent
    for obs in sim.observations:
        back = rts.read_prism_file(out / f"prism{obs.prism}.csv", station=obs.station,
                                   prism=obs.prism, additive_constant=0.01)
        for name in ("t", "hz", "v", "d"):
            np.testing.assert_array_equal(getattr(back, name), getattr(obs, name))
        np.testing.assert_array_equal(back.distance, obs.distance)
    g = rts.read_gcp_rts_project(out / "GCP.txt", additive_constant=0.01)
    for name in ("station", "marker"):
        assert list(getattr(g, name)) == list(getattr(sim.gcp, name))
    for name in ("hz", "v", "d", "t"):
        np.testing.assert_array_equal(getattr(g, name), getattr(sim.gcp, name))
    weather = pytest.importorskip("rtsgt.io.weather")
    w = weather.read_weather_csv(out / "weather.csv")
    np.testing.assert_array_equal(w.pressure_hpa, sim.weather_reported.pressure_hpa)
    survey = pytest.importorskip("rtsgt.io.survey")
    if hasattr(survey, "read_survey_raw"):
        s = survey.read_survey_raw(out / "calibration_raw.csv")
        np.testing.assert_allclose(s.xyz, sim.survey.xyz, rtol=0, atol=1e-13)
        np.testing.assert_allclose(s.xyz[:3], sim.truth.reference_body, rtol=0, atol=5e-3)


def test_refuses_existing_directory_and_replaces_with_overwrite(tmp_path):
    sim = simulate_deployment(SimulationConfig(duration_s=20.0, truth_rate_hz=10.0), 1)
    out = tmp_path / "d"
    out.mkdir()
    write_deployment(sim, out)  # an empty directory is fine
    with pytest.raises(InputError, match="not empty"):
        write_deployment(sim, out)
    write_deployment(sim, out, overwrite=True)  # an earlier output of rtsgt is replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]
    (out / "extra.txt").write_text("x")  # a file rtsgt did not write: never deleted
    with pytest.raises(InputError, match="extra.txt, which rtsgt did not write"):
        write_deployment(sim, out, overwrite=True)
    assert (out / "extra.txt").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a directory"):
        write_deployment(sim, f, overwrite=True)


def test_cli_simulate(tmp_path):
    from rtsgt.cli.main import app

    runner = CliRunner()
    out = tmp_path / "sim"
    res = runner.invoke(app, ["simulate", str(out), "--seed", "3", "--duration", "30"])
    assert res.exit_code == 0, res.output
    assert "deployment.toml" in res.output and "prism1.csv" in res.output
    doc = tomllib.loads((out / "deployment.toml").read_text())
    assert doc["deployment"]["name"] == "sim-seed-3"
    first = (out / "truth.tum").read_text()
    # the same seed gives the same files
    res = runner.invoke(app, ["simulate", str(out), "--seed", "3", "--duration", "30",
                              "--force"])
    assert res.exit_code == 0, res.output
    assert (out / "truth.tum").read_text() == first
    # an existing non-empty directory is refused without --force
    res = runner.invoke(app, ["simulate", str(out)])
    assert res.exit_code != 0
    assert res.stderr.startswith("error: ") and "--force" in res.stderr
    res = runner.invoke(app, ["simulate", str(tmp_path / "four"), "--stations", "4",
                              "--duration", "20"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "four" / "prism4.csv").is_file()
    res = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--stations", "9"])
    assert res.exit_code != 0 and "at most 5 stations" in res.stderr
