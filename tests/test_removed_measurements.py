"""What the filters removed: module masks -> RunRecord.removed -> measurements/removed.csv.

A simulated deployment with gross outliers, to which invalid statuses, a non-finite distance
and a duplicated time are added, is run through the pipeline. ``removed.csv`` must list exactly
the measurements that are not in the tracks, each with the module that removed it and its
reason, as the sequential references of ``test_filtering`` give them. The outliers module 1
lets through (jumps the rate gates allow) give poses the distance gate
rejects, and the measurements of their windows are left out of the GP fits (module 4).
"""

from __future__ import annotations

import csv
import dataclasses
from collections import Counter

import numpy as np
import pytest

from rtsgt.filtering import FilterParams, module1
from rtsgt.filtering.gates import in_windows
from rtsgt.filtering.modules import removed_measurements
from rtsgt.geometry.transform import RigidTransform
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import read_run, write_run
from rtsgt.measurement.polar import polar_to_cartesian
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import Observations
from test_filtering import ref_module1, ref_module2

#: Measurements of each station given a non-zero status, a NaN distance, a duplicated time
#: (as fractions of the series, away from its ends).
STATUS_AT, NAN_AT, DUPLICATE_AT = (0.2, 0.55), (0.4,), (0.7,)


def _inject(o: Observations, outlier: np.ndarray) -> tuple[Observations, dict[int, str]]:
    """Invalid statuses, a NaN and a duplicated time, on measurements that are neither
    outliers nor next to one; returns the new series and {index: expected module-1 reason}."""
    n = len(o)
    clean = ~(outlier | np.roll(outlier, 1) | np.roll(outlier, -1))

    def near(f):
        i = int(f * n)
        while not (clean[i] and clean[i - 1]):
            i += 1
        return i

    t, d, status = o.t.copy(), o.d.copy(), np.zeros(n, dtype=int)
    expected = {}
    for f in STATUS_AT:
        status[near(f)] = 3
        expected[near(f)] = "status"
    for f in NAN_AT:
        d[near(f)] = np.nan
        expected[near(f)] = "non_finite"
    for f in DUPLICATE_AT:
        i = near(f)
        t[i] = t[i - 1]
        expected[i] = "duplicate_time"
    return Observations(t, o.hz, o.v, d, status, o.station, o.prism, o.additive_constant,
                        o.source), expected


@pytest.fixture(scope="module")
def outlier_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("removed")
    cfg = SimulationConfig(duration_s=90.0, outlier_probability=0.03)
    sim = simulate_deployment(cfg, np.random.default_rng(4))
    data, opts = load_deployment(write_deployment(sim, tmp / "dep"))
    observations, injected, outliers = [], {}, {}
    for o in data.observations:
        outlier = np.asarray(sim.truth.observations[o.station].outlier, dtype=bool)
        assert outlier.shape == (len(o),)
        new, expected = _inject(o, outlier)
        observations.append(new)
        injected[o.station], outliers[o.station] = expected, outlier
    data = dataclasses.replace(data, observations=tuple(observations))
    opts = opts.updated(engine="linear", seed=4)
    result = run_pipeline(data, opts)
    out = write_run(result, tmp / "run")
    with open(out / "measurements" / "removed.csv", encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return result, out, rows, injected, outliers


def _expected(result):
    """Per station, the stage and reason of every raw measurement ("" when kept), from the
    sequential references of test_filtering (no mask of the modules is used)."""
    p = result.options.filter
    expected, kept1 = {}, {}
    for o in result.computation.data.observations:
        why, _ = ref_module1(o.t.tolist(), o.hz.tolist(), o.v.tolist(), o.distance.tolist(),
                             o.status.tolist(), p)
        expected[o.station] = [("module1", r) if r else ("", "") for r in why]
        kept1[o.station] = [i for i, r in enumerate(why) if not r]
    stations = [o.station for o in result.computation.data.observations]
    times = [[float(result.computation.data.observations[k].t[i]) for i in kept1[s]]
             for k, s in enumerate(stations)]
    _, _, reasons2 = ref_module2(times, p)
    windows = result.computation.filter_reports["module4"].windows
    for k, (s, why2) in enumerate(zip(stations, reasons2, strict=True)):
        inside = in_windows(times[k], windows)
        for i, r, w in zip(kept1[s], why2, inside, strict=True):
            if r:
                expected[s][i] = ("module2", r)
            elif w:
                expected[s][i] = ("module4", "distance_window")
    return expected


def test_masks_reproduce_the_counts_and_the_kept_series(outlier_run):
    result, *_ = outlier_run
    reps = result.computation.filter_reports
    for o in result.computation.data.observations:
        rep = reps[f"module1_station{o.station}"]
        (mask,), (why,) = rep.kept_masks, rep.reasons
        assert mask.shape == why.shape == (len(o),) and int(mask.sum()) == rep.n_kept
        assert {r: int(np.sum(why == r)) for r in rep.removed} == dict(rep.removed)
        kept, _ = module1(o, result.options.filter)
        np.testing.assert_array_equal(o.t[mask], kept.t)
    rep2, rep4 = reps["module2"], reps["module4"]
    assert len(rep2.kept_masks) == len(rep4.kept_masks) == len(result.computation.tracks)
    for mask, why, c, mask4, tr in zip(rep2.kept_masks, rep2.reasons, rep2.per_series,
                                       rep4.kept_masks, result.computation.tracks.values(),
                                       strict=True):
        assert int(mask.sum()) == mask4.size and int(mask4.sum()) == len(tr)
        assert {r: int(np.sum(why == r)) for r in c} == dict(c)
    n1 = sum(r.n_removed for k, r in reps.items() if k.startswith("module1"))
    assert np.sum(result.removed.stage == "module1") == n1
    assert np.sum(result.removed.stage == "module2") == rep2.n_removed
    assert np.sum(result.removed.stage == "module4") == rep4.n_removed > 0
    # the injected faults and the outliers are all there to be removed
    assert all(reps[f"module1_station{o.station}"].removed[r] > 0
               for o in result.computation.data.observations for r in ("status", "non_finite",
                                                             "duplicate_time", "rate_distance"))


def test_removed_csv_lists_exactly_what_is_not_in_the_tracks(outlier_run):
    result, _, rows, _, _ = outlier_run
    raw = Counter((o.prism, f"{t:.9f}") for o in result.computation.data.observations for t in o.t)
    tracked = Counter((tr.prism, f"{t:.9f}") for tr in result.computation.tracks.values() for t in tr.t)
    listed = Counter((r["prism"], r["t"]) for r in rows)
    assert tracked + listed == raw
    assert sum(listed.values()) == len(rows) == len(result.removed) > 0
    ts = [float(r["t"]) for r in rows]
    assert ts == sorted(ts)


def test_removed_csv_gives_the_stage_and_reason_of_each(outlier_run):
    result, _, rows, injected, outliers = outlier_run
    expected = _expected(result)
    by_station = {o.station: o for o in result.computation.data.observations}
    T = result.computation.calibration.transforms
    got: dict[str, list] = {s: [] for s in by_station}
    out_rows = []
    for r in rows:
        got[r["station"]].append(r)
    for s, o in by_station.items():
        idx = [i for i, e in enumerate(expected[s]) if e[0]]
        # rows of a station are in measurement order (the sort by time is stable)
        assert len(got[s]) == len(idx)
        xyz = T[s].apply(polar_to_cartesian(o.hz[idx], o.v[idx], o.distance[idx]))
        for k, (i, r) in enumerate(zip(idx, got[s], strict=True)):
            assert (r["stage"], r["reason"]) == expected[s][i], (s, i, r)
            assert r["t"] == f"{o.t[i]:.9f}" and r["prism"] == o.prism
            if np.all(np.isfinite(xyz[k])):
                np.testing.assert_allclose([float(r[c]) for c in "xyz"], xyz[k], atol=1e-6)
        # independent of the references: what was injected, and the simulated outliers
        for i, reason in injected[s].items():
            assert expected[s][i] == ("module1", reason)
        out_rows += [expected[s][i] for i in np.flatnonzero(outliers[s])]
    # most outliers jump by more than the gate allows (a small jump against the motion, or the
    # first measurement of a block, passes module 1)
    assert out_rows.count(("module1", "rate_distance")) >= 0.7 * len(out_rows) > 10
    stages = {(r["stage"], r["reason"]) for r in rows}
    assert {("module1", "status"), ("module1", "non_finite"), ("module1", "duplicate_time"),
            ("module1", "rate_distance"), ("module2", "not_all_tracked"),
            ("module4", "distance_window")} <= stages


def test_the_reader_takes_removed_csv_with_and_without_the_reason_column(outlier_run, tmp_path):
    result, out, rows, _, _ = outlier_run
    data = read_run(out)
    rm = result.removed
    np.testing.assert_allclose(data.removed.t, rm.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(data.removed.xyz, rm.xyz, atol=1e-6)
    np.testing.assert_array_equal(data.removed.stage, rm.stage)
    np.testing.assert_array_equal(data.removed.prism, rm.prism)
    np.testing.assert_array_equal(data.removed.station, rm.station)
    np.testing.assert_array_equal(data.removed.reason, rm.reason)  # the record keeps them
    assert [r["reason"] for r in rows] == rm.reason.tolist()
    # a run of an earlier version: no reason column
    old = tmp_path / "old"
    old.mkdir()
    for f in out.rglob("*"):
        if f.is_file():
            dest = old / f.relative_to(out)
            dest.parent.mkdir(parents=True, exist_ok=True)
            dest.write_bytes(f.read_bytes())
    path = old / "measurements" / "removed.csv"
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[0] == "t,prism,station,x,y,z,stage,reason"
    path.write_text("".join(ln.rsplit(",", 1)[0] + "\n" for ln in lines), encoding="utf-8")
    again = read_run(old)
    np.testing.assert_array_equal(again.removed.t, data.removed.t)
    np.testing.assert_array_equal(again.removed.xyz, data.removed.xyz)
    np.testing.assert_array_equal(again.removed.stage, data.removed.stage)
    np.testing.assert_array_equal(again.removed.station, data.removed.station)
    assert set(again.removed.reason.tolist()) == {""}  # what the older file did not say


def test_removed_measurements_from_masks_by_hand():
    """Two stations, identity calibrations: every stage and reason, sorted by time."""
    p = FilterParams()
    t = np.arange(10.0)
    d = np.full(10, 20.0)
    d[3] = 30.0  # a distance jump: rate_distance
    status = np.zeros(10, dtype=int)
    status[6] = 2
    a = Observations(t, np.full(10, 1.0), np.full(10, 1.5), d, status, "1", "1")
    b = Observations(t + 0.5, np.full(10, 2.0), np.full(10, 1.4), np.full(10, 15.0), None,
                     "2", "2")
    (ka, ra), (kb, rb) = module1(a, p), module1(b, p)
    m2 = [np.ones(len(ka), bool), np.ones(len(kb), bool)]
    m2[0][-1] = False  # the last kept of station 1 (t = 9)
    m2[1][:2] = False  # the first two of station 2 (t = 0.5, 1.5)
    why2 = [np.where(m, "", "not_all_tracked") for m in m2]
    why2[1][1] = "short_interval"
    T = {"1": RigidTransform.identity(), "2": RigidTransform.identity()}
    rm = removed_measurements([a, b], [ra, rb], m2, why2, T)
    assert rm.t.tolist() == [0.5, 1.5, 3.0, 6.0, 9.0]
    assert rm.station.tolist() == ["2", "2", "1", "1", "1"]
    assert rm.stage.tolist() == ["module2", "module2", "module1", "module1", "module2"]
    assert rm.reason.tolist() == ["not_all_tracked", "short_interval", "rate_distance",
                                  "status", "not_all_tracked"]
    np.testing.assert_array_equal(rm.xyz[2], polar_to_cartesian(1.0, 1.5, 30.0))
    empty = removed_measurements([b], [rb], [np.ones(len(kb), bool)], [np.full(len(kb), "")],
                                 T)
    assert len(empty) == 0 and empty.xyz.shape == (0, 3)
    # module 4: measurements module 2 kept, left out of the GP fits
    m4 = [np.zeros(int(m.sum()), bool) for m in m2]
    m4[1][0] = True  # station 2's first measurement module 2 kept (t = 2.5)
    rm = removed_measurements([a, b], [ra, rb], m2, why2, T, m4)
    assert rm.t.tolist() == [0.5, 1.5, 2.5, 3.0, 6.0, 9.0]
    assert rm.stage.tolist()[2] == "module4" and rm.reason.tolist()[2] == "distance_window"
    with pytest.raises(ValueError, match="outlier mask"):
        removed_measurements([a, b], [ra, rb], m2, why2, T, [m4[0], m4[1][1:]])
    with pytest.raises(ValueError, match="masks do not match"):
        removed_measurements([a], [ra], [np.ones(3, bool)], [np.full(3, "")], T)
