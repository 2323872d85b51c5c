"""rtsgt.options: the one rule every option value meets, and one random stream per stage."""

from __future__ import annotations

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.options import (
    RANDOM_STAGES,
    InterpolationOptions,
    PoseOptions,
    RunOptions,
    stage_rng,
)


def test_each_stage_has_its_own_stream_the_children_of_the_seed():
    children = np.random.SeedSequence(42).spawn(len(RANDOM_STAGES))
    draws = {}
    for stage, child in zip(RANDOM_STAGES, children, strict=True):
        x = stage_rng(42, stage).standard_normal(8)
        np.testing.assert_array_equal(x, np.random.default_rng(child).standard_normal(8))
        draws[stage] = x
    # distinct streams, and none is the plain default_rng(seed) the stages used to share
    plain = np.random.default_rng(42).standard_normal(8)
    for a in RANDOM_STAGES:
        assert not np.allclose(draws[a], plain)
        for b in RANDOM_STAGES:
            assert a == b or not np.allclose(draws[a], draws[b])
    with pytest.raises(ValueError):
        stage_rng(42, "no-such-stage")


@pytest.mark.parametrize("change, match", [
    ({"seed": -1}, "seed"), ({"seed": 1.5}, "seed"), ({"seed": True}, "seed"),
    ({"samples": 9}, "samples"), ({"samples": 10.0}, "samples"),
    ({"rate_hz": 0.0}, "rate_hz"), ({"rate_hz": float("nan")}, "rate_hz"),
    ({"rate_hz": float("inf")}, "rate_hz"), ({"max_gap_s": 0.0}, "max_gap_s"),
    ({"distance_gate_m": float("nan")}, "distance_gate_m"), ({"engine": "foo"}, "engine"),
    ({"qc": -1.0}, "qc"), ({"qc": "maybe"}, "qc"), ({"gp_noise": "some"}, "gp_noise"),
    ({"registration": "svd"}, "registration"),
])
def test_bad_values_are_refused_naming_the_option(change, match):
    with pytest.raises(InputError, match=match):
        RunOptions().updated(**change)


def test_the_nested_records_take_the_flat_names_of_the_command_line():
    o = RunOptions().updated(engine="ut", samples=50, seed=3, rate_hz=2.0, qc="likelihood",
                             gp_noise="all", distance_gate_m=0.5, registration="unweighted")
    assert o == RunOptions(seed=3, interpolation=InterpolationOptions(2.0, "likelihood",
                                                                      gp_noise="all"),
                           pose=PoseOptions("ut", 50, distance_gate_m=0.5,
                                            registration="unweighted"))
    assert RunOptions().updated() == RunOptions()
    with pytest.raises(TypeError, match="no_such"):
        RunOptions().updated(no_such=1)


def test_limits_may_be_switched_off_with_infinity():
    o = RunOptions().updated(max_gap_s=float("inf"), distance_gate_m=float("inf"))
    assert o.interpolation.max_gap_s == float("inf") and o.pose.distance_gate_m == float("inf")


def test_a_configuration_without_options_gets_the_owners_defaults(tmp_path):
    """Defaults are written once: a TOML without [noise], [filter], [interpolation] and [pose]
    gives exactly RunOptions(), FilterParams() and NoiseModel()'s values."""
    import re

    from rtsgt.filtering import FilterParams
    from rtsgt.io.deployment import load_deployment
    from rtsgt.noise import NoiseModel
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

    sim = simulate_deployment(SimulationConfig(duration_s=30.0), np.random.default_rng(1))
    toml = write_deployment(sim, tmp_path / "dep")
    text = toml.read_text()
    for table in ("noise", "filter", "interpolation", "pose"):
        text = re.sub(rf"(?ms)^\[{table}\]\n.*?(?=^\[|\Z)", "", text)
    assert "[pose]" not in text and "tau_r_m_s" not in text
    bare = tmp_path / "dep" / "bare.toml"
    bare.write_text(text)
    _, o = load_deployment(bare)
    assert o.interpolation == InterpolationOptions() and o.pose == PoseOptions()
    assert o.filter == FilterParams()
    model = NoiseModel(instrument=o.noise.instrument)
    for name in ("sources", "time_sync_mean_s", "time_sync_std_s", "temperature_halfwidth_c",
                 "pressure_halfwidth_hpa", "humidity_halfwidth_pct"):
        assert getattr(o.noise, name) == getattr(model, name), name


def test_the_paper_profile_sets_the_papers_switches_and_explicit_values_win():
    base = RunOptions()
    paper = base.updated(profile="paper")
    # where rtsgt's defaults differ from the published method, the profile switches them back
    assert (paper.interpolation.gp_noise, paper.interpolation.motion_prior,
            paper.interpolation.outlier_windows, paper.pose.registration) == \
        ("all", "constant", "keep", "unweighted")
    assert (base.interpolation.gp_noise, base.interpolation.motion_prior,
            base.interpolation.outlier_windows, base.pose.registration) == \
        ("white", "classes", "remove", "weighted")
    # everything the profile does not name is untouched; a value given with it wins
    assert paper.pose.engine == base.pose.engine and paper.filter == base.filter
    assert base.updated(profile="paper", registration="weighted").pose.registration == "weighted"
    with pytest.raises(InputError, match="'paper'"):
        base.updated(profile="papers")
