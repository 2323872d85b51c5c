"""Silent surprises of a run that must be said: in the terminal and in ``summary.json``.

- a weather record that does not cover the measurement times;
- a surveyed inter-prism distance the tracking disagrees with beyond its predicted sigma;
- a run directory with a file missing (``rtsgt analyze`` / ``report`` read it back).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rtsgt.cli.main import app
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import read_run, run_summary, write_run
from rtsgt.io.weather import read_weather_csv, write_weather_csv
from rtsgt.pipeline import run_pipeline
from rtsgt.pose.reference import ReferencePoints
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import WeatherSeries

runner = CliRunner()


def _deployment(tmp_path: Path, seed: int, duration: float) -> Path:
    sim = simulate_deployment(SimulationConfig(duration_s=duration), np.random.default_rng(seed))
    return write_deployment(sim, tmp_path / f"dep{seed}")


def _run(data, opts, seed: int):
    return run_pipeline(data, opts.updated(engine="linear", seed=seed))


def _stale_weather(cfg: Path, hours_before_end: float) -> WeatherSeries:
    """Replace the deployment's weather by hourly records that end ``hours_before_end`` h
    before the first measurement (the same values, the times moved back)."""
    path = cfg.parent / "weather.csv"
    w = read_weather_csv(path)
    data, _ = load_deployment(cfg)
    t0 = min(float(o.t[0]) for o in data.observations)
    t = t0 - hours_before_end * 3600.0 - 3600.0 * np.arange(len(w.t))[::-1]
    stale = WeatherSeries(t, w.temperature_c, w.pressure_hpa, w.humidity_pct)
    write_weather_csv(path, stale)
    return stale


# -- 1. weather coverage --------------------------------------------------------------------


def test_weather_that_covers_the_run_is_recorded_without_warning(tmp_path):
    cfg = _deployment(tmp_path, 3, 60.0)
    data, opts = load_deployment(cfg)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = _run(data, opts, 3)
    assert not [w for w in caught if "weather" in str(w.message)]
    summary = run_summary(result)
    w = summary["weather"]
    assert w["file"] == str(cfg.parent / "weather.csv")
    assert w["first_t_s"] == data.weather.t[0] and w["last_t_s"] == data.weather.t[-1]
    assert w["sampling_interval_s"] == 3600.0
    assert w["covered"] is True and w["uncovered_measurements"] == 0
    # the block cross-validation may find the motion prior too cautious while the simulated
    # robot drives steadily (its smooth motion is not a WNOA process; docs/self-checks.md)
    assert [m for m in summary["warnings"]
            if not m.startswith("self-check, block cross-validation")] == []


def test_weather_ending_hours_before_the_run_warns_through_the_cli(tmp_path):
    """Hourly records that end 3 h before tracking: the measurements lie 3 h (and up to the
    run's 60 s more) beyond the last record, more than one record interval: a warning that
    names the file and says how far; summary.json records the file, its span and the warning,
    and the terminal shows the warning once."""
    cfg = _deployment(tmp_path, 3, 60.0)
    stale = _stale_weather(cfg, 3.0)
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(cfg), "-o", str(out), "--engine", "linear"])
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    w = summary["weather"]
    assert w["file"] == str(cfg.parent / "weather.csv")
    assert (w["first_t_s"], w["last_t_s"]) == (stale.t[0], stale.t[-1])
    assert w["covered"] is False
    assert 3 * 3600.0 <= w["after_last_s"] <= 3 * 3600.0 + 61.0
    assert w["uncovered_measurements"] == w["measurements"] > 0
    said = [m for m in summary["warnings"] if "weather" in m]
    assert len(said) == 1
    assert str(cfg.parent / "weather.csv") in said[0] and "3.0 h after the last record" in said[0]
    assert res.stderr.count("warning: weather") == 1
    assert "3.0 h after the last record" in res.stderr


def test_weather_a_few_minutes_past_the_last_hourly_record_is_covered(tmp_path):
    """20 minutes after the last hourly record is within one record interval: no warning."""
    cfg = _deployment(tmp_path, 3, 60.0)
    _stale_weather(cfg, 20 / 60)
    data, opts = load_deployment(cfg)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = _run(data, opts, 3)
    assert not [w for w in caught if "weather" in str(w.message)]
    assert run_summary(result)["weather"]["covered"] is True


# -- 2. surveyed inter-prism distances --------------------------------------------------------


@pytest.fixture(scope="module")
def sim_data(tmp_path_factory):
    cfg = _deployment(tmp_path_factory.mktemp("dist"), 7, 120.0)
    return load_deployment(cfg)


def _shifted(ref: ReferencePoints, name: str, towards: str, shift_m: float) -> ReferencePoints:
    """The reference with prism ``name`` moved ``shift_m`` away from prism ``towards``."""
    i, j = ref.names.index(name), ref.names.index(towards)
    xyz = ref.xyz.copy()
    u = (xyz[i] - xyz[j]) / np.linalg.norm(xyz[i] - xyz[j])
    xyz[i] += shift_m * u
    return ReferencePoints(ref.names, xyz, ref.cov, ref.frame)


def test_consistent_survey_distances_pass_silently(sim_data):
    data, opts = sim_data
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = _run(data, opts, 7)
    assert not [w for w in caught if "surveyed distance" in str(w.message)]
    pairs = run_summary(result)["inter_prism_distances"]
    assert set(pairs) == {"1-2", "1-3", "2-3"}
    for p in pairs.values():
        assert abs(p["ratio"]) < 3.0
        assert 0.1 < p["predicted_sigma_mm"] < 20.0
        assert p["poses"] == int(result.computation.keep.sum())


def test_a_survey_off_by_3_cm_warns_and_is_recorded(sim_data, tmp_path):
    data, opts = sim_data
    bad = dataclasses.replace(data, reference=_shifted(data.reference, "1", "2", 0.03))
    with pytest.warns(RtsgtWarning, match=r"prisms 1-2: the surveyed distance"):
        result = _run(bad, opts, 7)
    pairs = run_summary(result)["inter_prism_distances"]
    # the tracked distance is 30 mm shorter than the (lengthened) surveyed one
    assert pairs["1-2"]["median_deviation_mm"] == pytest.approx(-30.0, abs=5.0)
    assert abs(pairs["1-2"]["ratio"]) > 3.0
    assert abs(pairs["2-3"]["ratio"]) < 3.0  # prisms 2 and 3 were not moved
    assert any("prisms 1-2" in m for m in result.warnings)
    out = write_run(result, tmp_path / "run")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["inter_prism_distances"]["1-2"]["ratio"] == pairs["1-2"]["ratio"]
    assert any("prisms 1-2: the surveyed distance" in m for m in summary["warnings"])


def test_pipeline_warnings_are_recorded_and_shown_once(sim_data):
    data, opts = sim_data
    bad = dataclasses.replace(data, reference=_shifted(data.reference, "1", "2", 0.03))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = _run(bad, opts, 7)
    shown = [str(w.message) for w in caught if issubclass(w.category, RtsgtWarning)]
    assert len(shown) == len(set(shown)) >= 1  # each once
    assert set(shown) <= set(result.warnings)
    # a second run in the same process records them again (no "already shown" registry)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = _run(bad, opts, 7)
    assert again.warnings == result.warnings


def test_warnings_before_a_failure_are_still_shown(tmp_path):
    """A run that fails after a warning (here: no query time inside the tracking) still shows
    the warning it had recorded."""
    cfg = _deployment(tmp_path, 3, 60.0)
    _stale_weather(cfg, 3.0)
    data, opts = load_deployment(cfg)
    late = dataclasses.replace(data, query_times=np.array([data.weather.t[0]]))
    with pytest.warns(RtsgtWarning, match=r"weather .*3\.0 h after the last record"):
        with pytest.raises(InputError, match="No query time"):
            _run(late, opts, 3)


# -- 3. a damaged run directory ----------------------------------------------------------------


@pytest.fixture(scope="module")
def written_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("written")
    data, opts = load_deployment(_deployment(tmp, 5, 60.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = _run(data, opts, 5)
    return write_run(result, tmp / "run")


def _copy(run: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(run, tmp_path / "copy"))


@pytest.mark.parametrize("missing", ["measurements/prism2.csv", "prisms/prism2.csv",
                                     "prisms/prism2_sources.csv"])
def test_a_missing_file_the_summary_lists_is_an_error(written_run, tmp_path, missing):
    run = _copy(written_run, tmp_path)
    (run / missing).unlink()
    with pytest.raises(InputError, match=r"missing.*summary\.json") as err:
        read_run(run)
    assert err.value.path == str(run / missing)


def test_a_missing_optional_file_warns(written_run, tmp_path):
    run = _copy(written_run, tmp_path)
    (run / "measurements" / "removed.csv").unlink()
    with pytest.warns(RtsgtWarning, match=r"removed\.csv.*missing"):
        data = read_run(run)
    assert data.removed.t.size == 0


def test_a_missing_measurement_file_without_summary_warns(written_run, tmp_path):
    """Without summary.json nothing says which files were written: a prism without its
    measurements is read with a warning naming the file, not silently."""
    run = _copy(written_run, tmp_path)
    (run / "summary.json").unlink()
    (run / "measurements" / "prism2.csv").unlink()
    with pytest.warns(RtsgtWarning, match=r"prism2\.csv"):
        data = read_run(run)
    assert set(data.measurements) == {"1", "3"}


def test_an_intact_run_reads_without_warning(written_run):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RtsgtWarning)
        data = read_run(written_run)
    assert set(data.measurements) == {"1", "2", "3"}
