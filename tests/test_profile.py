"""The paper's preset where users set options: ``profile = "paper"`` at the top of the
deployment TOML, ``rtsgt run --profile paper`` / ``rtsgt batch --profile paper``, and
:func:`rtsgt.app.run_deployment`'s ``profile`` (docs/honesty.md#the-papers-switches,
docs/file-formats.md#deployment-toml, docs/cli.md#configuration).

A switch given with the profile wins over it, in the file and on the command line; the
command line's profile replaces the file's switches.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from _paths import EXAMPLE_DIR
from rtsgt.app import run_deployment
from rtsgt.batch import BatchTask, run_task
from rtsgt.cli.main import app
from rtsgt.errors import ConfigError
from rtsgt.io.config import load_config
from rtsgt.io.run_dir import read_summary
from rtsgt.options import PROFILES, RunOptions
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

PAPER = RunOptions().updated(profile="paper")


def _switches(options: RunOptions) -> dict:
    """The values of the paper's switches in ``options``, by flat name."""
    records = (options.calibration, options.interpolation, options.pose)
    return {k: next(getattr(r, k) for r in records if hasattr(r, k)) for k in PROFILES["paper"]}


@pytest.fixture
def example(tmp_path):
    """A copy of the shipped excerpt (its TOML to edit)."""
    shutil.copytree(EXAMPLE_DIR, tmp_path / "dep")
    return tmp_path / "dep" / "deployment.toml"


def test_the_profile_key_of_the_toml_sets_the_papers_switches_and_a_table_key_wins(example):
    text = example.read_text()
    assert _switches(load_config(example).options) != _switches(PAPER)  # rtsgt's defaults
    example.write_text('profile = "paper"\n' + text)
    assert _switches(load_config(example).options) == _switches(PAPER)
    example.write_text('profile = "paper"\n'
                       + text.replace("[pose]\n", '[pose]\nregistration = "weighted"\n'))
    got = _switches(load_config(example).options)
    assert got == {**_switches(PAPER), "registration": "weighted"}


@pytest.mark.parametrize("edit, message", [
    (lambda t: 'profile = "papr"\n' + t, "profile = 'papr' is not one of 'paper'"),
    (lambda t: 'profile = 3\n' + t, "profile = 3 is not one of 'paper'"),
    (lambda t: t.replace("[pose]\n", '[pose]\nprofile = "paper"\n'),
     "[pose] profile = 'paper': the run's profile is a key of the file's top"),
    (lambda t: t.replace('profile = "trimble-s7"', 'profile = "paper"'),
     "[instrument] profile = 'paper': the run's profile is a key of the file's top"),
])
def test_a_bad_or_misplaced_profile_is_one_line_naming_the_file(example, edit, message):
    example.write_text(edit(example.read_text()))
    with pytest.raises(ConfigError) as info:
        load_config(example)
    assert message in str(info.value) and str(example) in str(info.value)


@pytest.fixture(scope="module")
def short_deployment(tmp_path_factory):
    """A simulated 30 s deployment (its TOML)."""
    sim = simulate_deployment(SimulationConfig(duration_s=30.0), np.random.default_rng(5))
    return write_deployment(sim, tmp_path_factory.mktemp("profile") / "deployment")


def test_run_profile_paper_on_the_command_line_and_a_switch_given_with_it(short_deployment,
                                                                          tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["run", str(short_deployment), "-o", str(out), "-q",
                                      "--engine", "linear", "--profile", "paper",
                                      "--registration", "weighted"])
    assert result.exit_code == 0, result.output
    options = read_summary(out).options
    assert _switches(options) == {**_switches(PAPER), "registration": "weighted"}
    assert options.pose.engine == "linear"


def test_a_bad_profile_is_a_usage_error_before_any_work(short_deployment, tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["run", str(short_deployment), "-o", str(out),
                                      "--profile", "papr"])
    assert result.exit_code == 2 and "--profile" in result.output
    assert "'paper'" in result.output and not out.exists()


def test_the_command_lines_profile_replaces_the_files_switches(short_deployment, tmp_path):
    """Python users and the batch: the profile over the file's (here: weighted) switch,
    checked before the run directory is looked at."""
    toml = short_deployment.with_name("weighted.toml")  # beside the data it names
    toml.write_text(short_deployment.read_text().replace(
        "[pose]\n", '[pose]\nregistration = "weighted"\n'))
    assert load_config(toml).options.pose.registration == "weighted"
    with pytest.raises(Exception, match="profile"):
        run_deployment(toml, tmp_path / "x", profile="papr")
    task = BatchTask("d", toml, tmp_path / "batch" / "d", 7, {"profile": "paper",
                                                             "engine": "linear"})
    outcome = run_task(task)
    assert outcome.status == "done", outcome.message
    options = read_summary(task.out).options
    assert _switches(options) == _switches(PAPER) and options.seed == 7
