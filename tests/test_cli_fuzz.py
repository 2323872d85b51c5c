"""Every command, driven with random bad values of its options and of the configuration's keys.

Whatever the value, a command must end with a status of the documented set (0 done, 1 bad
input, 2 bad command line), print no traceback, print at most one ``error: ...`` line (exactly
one when it fails), and leave its output path either absent or a complete output of rtsgt
(a manifest listing what it wrote). Hypothesis draws the values (derandomised: the same
examples on every machine); the values are bad or borderline on purpose (non-numbers, nan,
infinities, zero, negatives, tiny numbers, wrong types), never large valid ones, which would
only make a long run.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from rtsgt.cli.main import app
from rtsgt.io.output_dir import MANIFEST

pytestmark = pytest.mark.slow
runner = CliRunner()
FUZZ = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])

#: Values of a command-line option: text as a user could type it.
BAD_TEXT = st.one_of(
    st.sampled_from(["0", "-0", "-1", "-5", "-1e-9", "nan", "NaN", "inf", "-inf", "1e309",
                     "1e-300", "", " ", "abc", "1,5", "0x10", "5Hz", "[1]", "None", "true",
                     "--", "-", "é", "1e", "3.", ".5", "+2"]),
    st.floats(max_value=0.0, allow_infinity=True).map(repr),
    st.integers(min_value=-10**9, max_value=0).map(str),
    st.text(max_size=6),
)

#: Values of a configuration key, as TOML.
BAD_TOML = st.one_of(
    st.sampled_from(["0", "-1", "-2.5", "nan", "inf", "-inf", "1e-300", "true", "false",
                     '""', '"abc"', '"0"', "[]", "[1, 2]", '["x"]', "{}", "{ a = 1 }",
                     "1979-05-27", '"nan"', '"instrument"']),
    st.floats(max_value=0.0, allow_nan=False, allow_infinity=False).map(repr),
    st.integers(min_value=-1000, max_value=0).map(str),
    st.text(alphabet="abcxyz_ -0123.", max_size=8).map(json.dumps),
)

#: Keys of a simulated deployment's TOML, with the table they are in.
TOML_KEYS = [
    ("deployment", "name"), ("deployment", "reference_station"),
    ("instrument", "profile"),
    ("gcp", "format"), ("gcp", "additive_constant_m"),
    ("weather", "format"),
    ("reference", "format"), ("reference", "body_frame"),
    ("noise", "sources"), ("noise", "time_sync_mean_s"), ("noise", "time_sync_std_s"),
    ("noise", "temperature_halfwidth_c"), ("noise", "pressure_halfwidth_hpa"),
    ("filter", "tau_r_m_s"), ("filter", "tau_a_deg_s"), ("filter", "tau_s_s"),
    ("filter", "tau_l_s"),
    ("interpolation", "rate_hz"), ("interpolation", "qc"), ("interpolation", "max_gap_s"),
    ("pose", "engine"), ("pose", "samples"), ("pose", "distance_gate_m"),
    ("pose", "uncertainty_gate_m"),
]


def check_outcome(r, out: Path | None = None) -> None:
    """The contract every command keeps, whatever it was given."""
    assert r.exit_code in (0, 1, 2), (r.exit_code, r.output, r.exception)
    assert "Traceback" not in r.output
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == (0 if r.exit_code == 0 else 1), r.stderr
    assert not [ln for ln in r.stderr.splitlines() if ln.startswith("Usage:")], r.stderr
    if out is None:
        return
    siblings = [p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]
    assert siblings == [], siblings  # no temporary directory left beside the output
    if out.exists():
        manifest = json.loads((out / MANIFEST).read_text())
        listed = set(manifest["files"])
        present = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
        assert present - {MANIFEST} == listed
        if manifest["kind"] == "run":
            assert {"summary.json", "groundtruth.tum", "groundtruth_covariance.csv"} <= listed


@pytest.fixture(scope="module")
def deployment(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz") / "dep"
    r = runner.invoke(app, ["simulate", str(folder), "--duration", "40", "--seed", "4"])
    assert r.exit_code == 0, r.output
    return folder


@pytest.fixture(scope="module")
def run_dir(deployment, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fuzzrun") / "run"
    r = runner.invoke(app, ["run", str(deployment / "deployment.toml"), "-o", str(out),
                            "--engine", "linear", "-q"])
    assert r.exit_code == 0, r.output
    return out


def _fresh(tmp_path: Path, name: str) -> Path:
    out = tmp_path / name
    if out.exists():
        shutil.rmtree(out)
    return out


RUN_OPTIONS = ["--rate", "--samples", "--engine", "--seed"]


@FUZZ
@given(option=st.sampled_from(RUN_OPTIONS), value=BAD_TEXT)
def test_run_options(deployment, tmp_path, option, value):
    out = _fresh(tmp_path, "out")
    args = ["run", str(deployment / "deployment.toml"), "-o", str(out), "-q", option, value]
    if option != "--engine":
        args += ["--engine", "linear"]
    check_outcome(runner.invoke(app, args), out)


@FUZZ
@given(option=st.sampled_from(["--duration", "--samples", "--engine", "--seed"]), value=BAD_TEXT)
def test_demo_options(tmp_path, option, value):
    out = _fresh(tmp_path, "demo")
    args = ["demo", "-o", str(out), "-q", "--no-report", option, value]
    if option != "--duration":
        args += ["--duration", "40"]
    if option != "--engine":
        args += ["--engine", "linear"]
    check_outcome(runner.invoke(app, args), out)


@FUZZ
@given(option=st.sampled_from(["--duration", "--stations", "--seed"]), value=BAD_TEXT)
def test_simulate_options(tmp_path, option, value):
    out = _fresh(tmp_path, "sim")
    args = ["simulate", str(out), option, value]
    if option != "--duration":
        args += ["--duration", "30"]
    check_outcome(runner.invoke(app, args), out)


EVALUATE_OPTIONS = ["--align", "--max-gap", "--delta", "--delta-unit", "--n-align", "--t-offset",
                    "--format", "--gt-mode", "--gt-engine"]


@FUZZ
@given(option=st.sampled_from(EVALUATE_OPTIONS), value=BAD_TEXT)
def test_evaluate_options(run_dir, tmp_path, option, value):
    out = _fresh(tmp_path, "plots")
    args = ["evaluate", str(run_dir), str(run_dir / "groundtruth.tum"), option, value,
            "--plot", str(out)]
    check_outcome(runner.invoke(app, args), out)


@FUZZ
@given(option=st.sampled_from(["--bins", "--samples", "--engine", "--pose-measure",
                               "--formats"]), value=BAD_TEXT)
def test_analyze_options(run_dir, tmp_path, option, value):
    out = _fresh(tmp_path, "analysis")
    args = ["analyze", str(run_dir), "--out", str(out), option, value]
    if option not in ("--engine", "--samples"):
        args += ["--engine", "linear"]
    if option != "--formats":
        args += ["--no-figures"]
    check_outcome(runner.invoke(app, args), out)


@FUZZ
@given(option=st.sampled_from(["--rate", "--qc", "--max-gap"]), value=BAD_TEXT)
def test_interpolate_options(run_dir, tmp_path, option, value):
    track = run_dir / "prisms" / "prism1.csv"
    out = tmp_path / "track.csv"
    if out.exists():
        out.unlink()
    r = runner.invoke(app, ["interpolate", str(track), option, value, "--out", str(out)])
    check_outcome(r)
    assert r.exit_code == 0 or not out.exists()


@FUZZ
@given(option=st.sampled_from(["--samples", "--reference-station", "--seed", "--format"]),
       value=BAD_TEXT)
def test_calibrate_options(tmp_path, option, value):
    out = tmp_path / "cal.json"
    if out.exists():
        out.unlink()
    r = runner.invoke(app, ["calibrate", "example", option, value, "--out", str(out)])
    check_outcome(r)
    assert r.exit_code == 0 or not out.exists()


def _set_key(text: str, table: str, key: str, value: str) -> str:
    """The TOML text with ``key`` of ``[table]`` set to ``value`` (added if absent)."""
    parts = re.split(r"(?m)^(?=\[)", text)
    for i, part in enumerate(parts):
        if part.startswith(f"[{table}]"):
            lines = [ln for ln in part.splitlines() if not re.match(rf"\s*{key}\s*=", ln)]
            lines.insert(1, f"{key} = {value}")
            parts[i] = "\n".join(lines) + "\n"
            return "".join(parts)
    return text + f"\n[{table}]\n{key} = {value}\n"


@FUZZ
@given(where=st.sampled_from(TOML_KEYS), value=BAD_TOML)
def test_configuration_keys(deployment, tmp_path, where, value):
    dep = tmp_path / "dep"
    if not dep.exists():
        shutil.copytree(deployment, dep)
    cfg = dep / "fuzz.toml"
    cfg.write_text(_set_key((dep / "deployment.toml").read_text(), *where, value))
    out = _fresh(tmp_path, "out")
    r = runner.invoke(app, ["run", str(cfg), "-o", str(out), "-q", "--engine", "linear"])
    check_outcome(r, out)
    if r.exit_code == 1:  # a bad configuration names its file
        assert str(cfg) in r.stderr or str(dep) in r.stderr, r.stderr
