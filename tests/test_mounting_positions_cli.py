"""``rtsgt evaluate GT EST --lever-arm x,y,z --estimate lever-xy,clock`` against a position-only
ground truth (one prism, issue 24 item 4): the prism's lever arm in the sensor frame and the
clock estimated with a drifting odometry's error modelled; the mounting rotation refused with
its reason (docs/evaluating.md#position-only-ground-truth-one-tracked-prism)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from rtsgt.cli.main import app
from rtsgt.io.positions import write_position_csv
from rtsgt.io.trajectory import write_tum
from rtsgt.types import PositionTrajectory
from test_evaluation_mounting import LEVER, R_BS, T0, drifting, truth

runner = CliRunner()
CLOCK = 0.15
#: The prism at the body origin: in the sensor frame, -R_bs^T t_body_sensor.
PRISM = -R_BS.T @ LEVER


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A prism's track (50 Hz, 1 mm) and a drifting odometry of the sensor, 60 s, 0.15 s late."""
    d = tmp_path_factory.mktemp("prism")
    tau = T0 + 0.02 * np.arange(4600)
    p, _ = truth(tau)
    gt = PositionTrajectory(tau, p, np.broadcast_to(np.eye(3) * 1e-6, (tau.size, 3, 3)).copy())
    write_position_csv(d / "prism.csv", gt)
    t = T0 + 5.0 + 0.1 * np.arange(600)
    est, _ = drifting(t, np.random.default_rng(31), clock=CLOCK, white_m=0.01)
    write_tum(d / "odom.tum", est)
    return d


def _evaluate(files, *extra):
    return runner.invoke(app, ["evaluate", str(files / "prism.csv"), str(files / "odom.tum"),
                               *extra])


def test_the_prisms_lever_arm_and_the_clock_are_estimated(files):
    r = _evaluate(files, f"--lever-arm=0,0,{PRISM[2]}", "--estimate", "lever-xy,clock",
                  "--json")
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    m = out["mounting"]
    assert m["estimated"] == ["lever-xy", "clock"] and m["fit"]["model"] == "odometry"
    assert m["lever_arm_frame"] == "sensor (estimate)" and m["lever_arm_sigma_m"][2] is None
    sig = np.array(m["lever_arm_sigma_m"][:2])
    assert np.all(np.abs(np.array(m["lever_arm_m"][:2]) - PRISM[:2]) < 4 * sig)
    assert m["lever_arm_m"][2] == pytest.approx(PRISM[2])
    assert abs(m["clock_offset_s"] - CLOCK) < 4 * m["clock_sigma_s"]
    assert m["clock_sigma_s"] < m["fit"]["max_sigma"]["clock"]
    assert out["association"]["time_offset_s"] == m["clock_offset_s"]
    assert out["lever_arm"]["source"] == "estimated"
    assert out["lever_arm"]["m"] == m["lever_arm_m"]
    assert np.array(out["lever_arm"]["cov_m2"])[2].tolist() == [0.0, 0.0, 0.0]


def test_the_readable_report_and_the_rotation_refused(files):
    r = _evaluate(files, f"--lever-arm=0,0,{PRISM[2]}", "--estimate", "lever-xy,clock")
    assert r.exit_code == 0, r.output
    assert "estimated" in r.output and "clock offset" in r.output
    r = _evaluate(files, "--lever-arm=0,0,0", "--estimate", "rotation,clock")
    assert r.exit_code != 0
    assert "only through the lever arm" in r.output and "Traceback" not in r.output
