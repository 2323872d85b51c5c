"""Deployment configuration: the real-excerpt configuration loads, bad ones fail clearly."""

from pathlib import Path

import numpy as np
import pytest

from _paths import EXAMPLE_TOML
from rtsgt.errors import ConfigError
from rtsgt.io.config import load_config

MINIMAL = """
[deployment]
reference_station = "1"
[[stations]]
id = "1"
prism = "1"
file = "p1.csv"
[[stations]]
id = "2"
prism = "2"
file = "p2.csv"
[[stations]]
id = "3"
prism = "3"
file = "p3.csv"
[gcp]
file = "gcp.txt"
[reference]
file = "survey.csv"
prisms = { "1" = 1, "2" = 2, "3" = 3 }
"""


def _in_reference(line: str):
    """An edit of :data:`MINIMAL` adding ``line`` to its ``[reference]`` section."""
    prisms = 'prisms = { "1" = 1, "2" = 2, "3" = 3 }'
    return lambda s: s.replace(prisms, f"{prisms}\n{line}")


@pytest.fixture
def deployment(tmp_path: Path) -> Path:
    for name in ("p1.csv", "p2.csv", "p3.csv", "gcp.txt", "survey.csv"):
        (tmp_path / name).write_text("x\n")
    cfg = tmp_path / "deployment.toml"
    cfg.write_text(MINIMAL)
    return cfg


def test_minimal_configuration_takes_the_paper_defaults(deployment):
    cfg = load_config(deployment)
    assert [s.prism for s in cfg.stations] == ["1", "2", "3"]
    assert cfg.stations[0].file == deployment.parent / "p1.csv"
    o = cfg.options
    assert o.filter.tau_r == 2.0 and o.filter.tau_s == 3.0 and o.filter.tau_l == 2.0
    assert o.filter.tau_a == np.radians(1.0) and o.filter.tau_e == np.radians(1.0)
    assert o.pose.distance_gate_m == 0.10 and o.pose.uncertainty_gate_m == 0.20
    assert o.interpolation.qc == "loo" and o.interpolation.rate_hz == 5.0
    assert o.interpolation.outlier_windows == "remove"
    assert cfg.query_times is None
    assert cfg.weather is None


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.replace('file = "p2.csv"', 'file = "nope.csv"'), r"no such file"),
        (lambda s: s.replace('reference_station = "1"', 'reference_station = "7"'),
         r"reference_station = '7' is not a station; known: 1, 2, 3"),
        (lambda s: s + '[pose]\nengine = "fast"\n', r"\[pose\] engine = 'fast': expected engine mc, ut, linear"),
        (lambda s: s + '[pose]\nregistration = "best"\n',
         r"\[pose\] registration = 'best': expected registration 'weighted' or 'unweighted'"),
        (lambda s: s + '[pose]\nsamples = "many"\n', r"samples must be int"),
        (lambda s: s + "[noise]\nsources = ['instrument', 'gravity']\n", r"unknown source\(s\) 'gravity'"),
        (lambda s: s + '[calibration]\nweighting = "best"\n',
         r"\[calibration\] weighting = 'best': expected a calibration weighting 'gls' or "
         r"'trace' or 'none'"),
        (lambda s: s + "[interpolation]\nqc = -1.0\n", r"\[interpolation\] qc = -1.0: expected qc > 0"),
        (lambda s: s + "[interpolation]\nqc = 'auto'\n", r"qc = 'auto': expected qc loo, likelihood or a number"),
        (lambda s: s + "[interpolation]\noutlier_windows = 'drop'\n",
         r"outlier_windows = 'drop': expected outlier_windows 'remove' or 'keep'"),
        (lambda s: s.replace('prisms = { "1" = 1, "2" = 2, "3" = 3 }', 'prisms = { "1" = 1, "2" = 2 }'),
         r"no survey row for tracked prism\(s\) 3"),
        (_in_reference("rocking_pivot = [0, 1]"),
         r"\[reference\] rocking_pivot must be \[x, y, z\] in m, got \[0, 1\]"),
        (_in_reference('rocking_pivot = [0, "a", 1]'),
         r"rocking_pivot must be \[x, y, z\] in m, got \[0, 'a', 1\]"),
        (_in_reference("prism_stability_mm = -2"),
         r"\[reference\] prism_stability_mm must be a finite mm >= 0, got -2.0"),
        (_in_reference('prism_stability_mm = "a"'),
         r"\[reference\] prism_stability_mm must be float, got 'a'"),
        (lambda s: s + "[filter]\ntau_r_m_s = 0\n", r"\[filter\] tau_r_m_s = 0.0: expected tau_r > 0"),
        (lambda s: s + "[filter]\ntau_x = 1\n", r"unknown key\(s\) tau_x"),
        (lambda s: s + "[cameras]\nx = 1\n", r"unknown section\(s\) cameras"),
        (lambda s: s.replace('prism = "2"', 'prism = "1"'), r"different prism"),
        (lambda s: s.replace("[gcp]", "[gcp_]"), r"unknown section"),
        (lambda s: s + "[pose\n", r"invalid TOML"),
    ],
)
def test_bad_configurations_name_the_problem(deployment, edit, message):
    deployment.write_text(edit(MINIMAL))
    with pytest.raises(ConfigError, match=message) as info:
        load_config(deployment)
    assert str(deployment) in str(info.value)


def test_missing_configuration_file(tmp_path):
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_config(tmp_path / "absent.toml")


def test_real_excerpt_configuration_loads():
    cfg = load_config(EXAMPLE_TOML)
    assert cfg.weather is not None and cfg.weather.format == "eccc"
    assert cfg.weather.utc_offset_hours == -5.0
    assert all(s.additive_constant_m == 0.01 for s in cfg.stations)


def test_the_calibration_weighting_is_the_papers_unless_asked(deployment):
    assert load_config(deployment).options.calibration.weighting == "none"
    deployment.write_text(MINIMAL + "[calibration]\nweighting = \"gls\"\n")
    assert load_config(deployment).options.calibration.weighting == "gls"


def test_the_outlier_windows_of_the_paper_stay_reachable(deployment):
    deployment.write_text(MINIMAL + "[interpolation]\noutlier_windows = \"keep\"\n")
    assert load_config(deployment).options.interpolation.outlier_windows == "keep"
