"""Raw total-station bags (ROS 1 and ROS 2) as the measurements of a deployment.

The bags are written here with ``rosbags``' own writers from the real excerpt's prism files
(the messages those files were extracted from: ``azimuth`` = ``Hz``, ``elevation`` = ``V``,
``distance`` = ``d``, ``header.stamp`` = ``t``; rtsgt/io/rts_bag.py), with the message
definitions a ROS 1 and a ROS 2 system carry (``Header header`` / ``std_msgs/Header header``,
``time`` / ``builtin_interfaces/Time``), not the reader's. Then:

- the whole pipeline gives the CSV route's ground truth through a ROS 1 and a ROS 2 bag
  (40 s of the excerpt, linear engine, same seed) to 1e-9 m, and ``rtsgt run`` on a bag
  deployment writes it with the reader's counts in ``summary.json``;
- messages with a non-zero status are removed and counted by reason;
- the older ``Float64MultiArray`` layout, the choice of the time stamp, a ROS 2 bag without its
  message definitions;
- bad input: one line naming the bag and the topic, exit status 1, no traceback.
"""

from __future__ import annotations

import json
import re
import sqlite3
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from _paths import EXAMPLE_DIR, EXCERPT
from rtsgt.cli.main import app
from rtsgt.errors import ConfigError, InputError, RtsgtWarning
from rtsgt.io.config import load_config
from rtsgt.io.deployment import load_deployment
from rtsgt.io.rts_bag import (
    CORRECTION_TOPIC,
    INPUT_REASONS,
    OLD_TOPIC,
    TOPIC,
    read_theodolite_bag,
)
from rtsgt.io.rts_project import read_prism_file
from rtsgt.io.trajectory import read_covariance_csv
from rtsgt.pipeline import run_pipeline

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

runner = CliRunner()

COORDS = "theodolite_node_msgs/msg/TheodoliteCoordsStamped"
CORRECTION = "theodolite_node_msgs/msg/TheodoliteTimeCorrection"
ARRAY = "std_msgs/msg/Float64MultiArray"
#: The definitions as a ROS 1 and a ROS 2 package would write them.
DEFINITIONS = {
    True: {COORDS: "Header header\ntime theodolite_time\nuint8 theodolite_id\nuint8 status\n"
                   "float64 azimuth\nfloat64 elevation\nfloat64 distance\n",
           CORRECTION: "Header header\nuint8 theodolite_id\nduration estimated_time_offset\n"},
    False: {COORDS: "std_msgs/Header header\nbuiltin_interfaces/Time theodolite_time\n"
                    "uint8 theodolite_id\nuint8 status\nfloat64 azimuth\nfloat64 elevation\n"
                    "float64 distance\n",
            CORRECTION: "std_msgs/Header header\nuint8 theodolite_id\n"
                        "builtin_interfaces/Duration estimated_time_offset\n"},
}
#: Seconds of the excerpt the pipeline runs on (a static part, a gap, a second static part).
SPAN_S = 40.0
#: Offset of each station's clock (its clock minus the receiver's, s): the node stamps
#: ``header.stamp = theodolite_time - estimated_time_offset`` (rtsgt/io/rts_bag.py).
CLOCK_OFFSET = {1: 0.125, 2: -0.0625, 3: 0.25}
#: Messages with a non-zero status injected per station: (status, values).
INVALID = [(1, (0.9, 1.5, 12.0)), (2, (0.9, 1.5, 40.0)), (3, (-1.0, -1.0, -1.0)),
           (3, (-1.0, -1.0, -1.0)), (4, (0.9, 1.5, 0.6)), (7, (0.9, 1.5, 12.0))]
#: The counts by reason those make per station.
INVALID_COUNTS = {"tilt_out_of_range": 1, "wrong_target_distance": 1, "tracking_exception": 2,
                  "distance_under_1m": 1, "unknown_status": 1}


def stamp(t: float) -> tuple[int, int]:
    """``(sec, nanosec)`` that read back (``sec + nanosec * 1e-9``) as ``t`` exactly."""
    sec = int(np.floor(t))
    ns = int(round((t - sec) * 1e9))
    for n in (ns, ns - 1, ns + 1, ns - 2, ns + 2):
        if 0 <= n < 1_000_000_000 and sec + n * 1e-9 == t:
            return sec, n
    raise AssertionError(f"no exact (sec, nanosec) for {t!r}")


def excerpt(span: float = SPAN_S) -> dict[int, np.ndarray]:
    """The excerpt's first ``span`` s per station: rows ``t d V Hz`` (the prism files)."""
    obs = {i: read_prism_file(EXCERPT / f"prism{i}.csv", station=i, prism=i) for i in (1, 2, 3)}
    t0 = min(o.t[0] for o in obs.values())
    return {i: np.column_stack([o.t, o.d, o.v, o.hz])[o.t < t0 + span] for i, o in obs.items()}


def messages(rows: dict[int, np.ndarray], invalid=INVALID, offsets=CLOCK_OFFSET) -> list:
    """The bag's messages ``(id, status, azimuth, elevation, distance, header t, theodolite t)``
    in order of reception: every valid row, and the invalid ones between them."""
    out = []
    for i, r in rows.items():
        for t, d, v, hz in r:
            out.append((i, 0, hz, v, d, t, t + offsets[i]))
        between = r[: len(invalid) + 1, 0]
        for k, (status, (hz, v, d)) in enumerate(invalid):
            t = 0.5 * (between[k] + between[k + 1])
            out.append((i, status, hz, v, d, t, t + offsets[i]))
    return sorted(out, key=lambda m: m[5])


def typestore(ros1: bool):
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    for name, text in DEFINITIONS[ros1].items():
        ts.register(get_types_from_msg(text, name))
    return ts


def write_bag(path: Path, ros1: bool, msgs: list, *, corrections=(), topic: str = TOPIC,
              msgtype: str = COORDS, array_size: int = 6,
              correction_topic: str = CORRECTION_TOPIC) -> Path:
    """A bag of ``msgs`` on ``topic`` (as :func:`messages` gives them) and the clock corrections
    ``(id, t, offset)`` on ``correction_topic``, written as the acquisition system records them
    (the older layout's as ``Float64MultiArray`` ``[sec, nsec, id, offset]``)."""
    ts = typestore(ros1)
    T = ts.types
    Time, Header, Duration = (T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"],
                              T["builtin_interfaces/msg/Duration"])

    def header(k, t):
        sec, ns = stamp(t)
        return (Header(seq=k, stamp=Time(sec=sec, nanosec=ns), frame_id="theodolite")
                if ros1 else Header(stamp=Time(sec=sec, nanosec=ns), frame_id="theodolite"))

    def encode(msg, name):
        return ts.serialize_ros1(msg, name) if ros1 else ts.serialize_cdr(msg, name)

    out = []
    for k, (i, status, hz, v, d, t, t_theo) in enumerate(msgs):
        if msgtype == COORDS:
            sec, ns = divmod(int(round(t_theo * 1e9)), 1_000_000_000)
            msg = T[COORDS](header=header(k, t), theodolite_time=Time(sec=sec, nanosec=ns),
                            theodolite_id=i, status=status, azimuth=hz, elevation=v, distance=d)
        elif msgtype == ARRAY:
            values = [i, hz, v, d, t] if array_size == 5 else [i, hz, v, d, *stamp(t)]
            values += [status] if array_size >= 7 else []
            data = np.array(values + [0.0] * (array_size - len(values)), dtype=np.float64)
            layout = T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
            msg = T[ARRAY](layout=layout, data=data)
        else:  # a pose where the measurements should be
            P = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=hz, y=v, z=d),
                                            orientation=T["geometry_msgs/msg/Quaternion"](
                                                x=0.0, y=0.0, z=0.0, w=1.0))
            msg = T[msgtype](header=header(k, t), pose=P)
        out.append((int(round(t * 1e9)), encode(msg, msgtype)))
    writer = Writer1(path) if ros1 else Writer2(path, version=8)
    with writer as w:
        conn = w.add_connection(topic, msgtype, typestore=ts)
        for ns, raw in out:
            w.write(conn, ns, raw)
        if corrections:
            kind = ARRAY if msgtype == ARRAY else CORRECTION
            cc = w.add_connection(correction_topic, kind, typestore=ts)
            for k, (i, t, off) in enumerate(corrections):
                sec, ns = divmod(int(round(off * 1e9)), 1_000_000_000)
                if kind == ARRAY:
                    layout = T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
                    msg = T[ARRAY](layout=layout, data=np.array([*stamp(t), i, off]))
                else:
                    msg = T[CORRECTION](header=header(k, t), theodolite_id=i,
                                        estimated_time_offset=Duration(sec=sec, nanosec=ns))
                w.write(cc, int(round(t * 1e9)), encode(msg, kind))
    return path


def corrections_of(rows: dict[int, np.ndarray]) -> list:
    """Two clock corrections per station, before and after the first measurement."""
    return [(i, float(r[0, 0]) + dt, CLOCK_OFFSET[i] + 1e-4 * k)
            for k, dt in enumerate((-5.0, 20.0)) for i, r in rows.items()]


def deployment(tmp_path: Path, *, bag: Path | None = None, rows=None, extra: str = "",
               stations: str | None = None) -> Path:
    """The excerpt's deployment with the prism files of ``rows`` or the measurements of
    ``bag``, the GCPs, weather and survey of the example."""
    text = (EXAMPLE_DIR / "deployment.toml").read_text(encoding="utf-8")
    head, tail = text.split("[[stations]]", 1)
    tail = tail[tail.index("[gcp]"):].replace('"data/', f'"{EXCERPT}/')
    if stations is None:
        stations = ""
        for i in (1, 2, 3):
            stations += f'[[stations]]\nid = "{i}"\nprism = "{i}"\nadditive_constant_m = 0.01\n'
            if bag is None:
                f = tmp_path / f"prism{i}.csv"  # the excerpt's first lines, verbatim
                lines = (EXCERPT / f"prism{i}.csv").read_text().splitlines(keepends=True)
                f.write_text("".join(lines[:len(rows[i])]))
                stations += f'file = "{f}"\n'
            stations += "\n"
    if bag is not None:
        extra = f'[measurements]\nfile = "{bag}"\nformat = "ros-bag"\n{extra}\n'
    path = tmp_path / ("bag.toml" if bag is not None else "csv.toml")
    path.write_text(head + extra + stations + tail, encoding="utf-8")
    return path


def run(config: Path):
    data, options = load_deployment(config)
    with warnings.catch_warnings():  # the self-checks' warnings on 40 s of data: not the point
        warnings.simplefilter("ignore")
        return data, run_pipeline(data, options.updated(engine="linear", samples=10, seed=7))


@pytest.fixture(scope="module")
def rows():
    return excerpt()


@pytest.fixture(scope="module")
def csv_route(rows, tmp_path_factory):
    """The CSV route's deployment data and run record."""
    return run(deployment(tmp_path_factory.mktemp("csv"), rows=rows))


def same_observations(a, b) -> None:
    for x, y in zip(a, b, strict=True):
        assert (x.station, x.prism, x.additive_constant) == (y.station, y.prism,
                                                             y.additive_constant)
        for name in ("t", "hz", "v", "d", "status"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=name)


# ------------------------------------------------------------------ the two routes agree


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_bag_route_gives_the_csv_ground_truth(ros1, rows, csv_route, tmp_path):
    bag = write_bag(tmp_path / ("run.bag" if ros1 else "run"), ros1, messages(rows),
                    corrections=corrections_of(rows))
    data, record = run(deployment(tmp_path, bag=bag))
    csv_data, csv_record = csv_route
    same_observations(data.observations, csv_data.observations)  # bit for bit
    gt, ref = record.groundtruth, csv_record.groundtruth
    assert len(gt) == len(ref) > 100
    np.testing.assert_array_equal(gt.t, ref.t)
    assert np.max(np.abs(gt.position - ref.position)) <= 1e-9
    assert np.max(np.abs(gt.quat_xyzw - ref.quat_xyzw)) <= 1e-12
    assert np.max(np.abs(gt.cov - ref.cov)) <= 1e-15
    rep = record.computation.filter_reports["input"]
    assert rep.removed == {r: 3 * n for r, n in INVALID_COUNTS.items()}
    assert [dict(c) for c in rep.per_series] == [INVALID_COUNTS] * 3
    assert rep.n_kept == sum(len(r) for r in rows.values())
    assert rep.n_in == rep.n_kept + 3 * len(INVALID)
    assert record.computation.filter_reports["module1_station1"].removed["status"] == 0


def test_rtsgt_run_on_a_bag(rows, csv_route, tmp_path):
    """``rtsgt run`` end to end: the ground truth of the CSV route, and what the reader
    removed and read in ``summary.json`` and the terminal table."""
    bag = write_bag(tmp_path / "run.bag", True, messages(rows), corrections=corrections_of(rows))
    out = tmp_path / "out"
    result = runner.invoke(app, ["run", str(deployment(tmp_path, bag=bag)), "-o", str(out),
                                 "--engine", "linear", "--samples", "10", "--seed", "7"],
                           env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    n = sum(len(r) for r in rows.values())
    assert re.search(rf"bag messages valid / read[ :│]+{n} / {n + 18} \(removed: "
                     r"tilt_out_of_range 3, wrong_target_distance 3, tracking_exception 6, "
                     r"distance_under_1m 3, unknown_status 3\)", result.stdout)
    got = read_covariance_csv(out / "groundtruth_covariance.csv")
    ref = csv_route[1].groundtruth
    np.testing.assert_array_equal(got.t, ref.t)
    assert np.max(np.abs(got.position - ref.position)) <= 1e-9
    summary = json.loads((out / "summary.json").read_text())
    read = summary["filters"]["input"]
    assert read["module"] == "input" and read["stations"] == ["1", "2", "3"]
    assert read["removed"] == {r: 3 * n for r, n in INVALID_COUNTS.items()}
    assert (read["format"], read["topic"], read["layout"], read["time"]) == (
        "ros-bag", TOPIC, "TheodoliteCoordsStamped", "header")
    assert read["theodolite_ids"] == {"1": 1, "2": 2, "3": 3}
    for s, off in CLOCK_OFFSET.items():
        corr = read["time_corrections"][str(s)]
        assert corr["count"] == 2
        assert corr["offset_s"]["first"] == pytest.approx(off, abs=1e-9)
        assert corr["offset_s"]["last"] == pytest.approx(off + 1e-4, abs=1e-9)
        assert read["stamp_difference_s"][str(s)] == pytest.approx(off, abs=1e-6)


def test_wild_first_shots_cost_no_measurement_and_leave_the_ground_truth(rows, csv_route,
                                                                        tmp_path):
    """A valid shot of 1234.5 m (beyond the largest distance) just before station 1's first
    measurement, and one of 234.5 m (under it: the rate gates' anchor) before station 2's: the
    run keeps every other measurement and gives the CSV route's ground truth."""
    msgs = messages(rows, invalid=())
    for i, d in ((1, 1234.5), (2, 234.5)):
        t0, _, v0, hz0 = rows[i][0]
        msgs.insert(0, (i, 0, hz0, v0, d, t0 - 0.2, t0 - 0.2 + CLOCK_OFFSET[i]))
    bag = write_bag(tmp_path / "wild.bag", True, msgs, corrections=corrections_of(rows))
    data, record = run(deployment(tmp_path, bag=bag))
    reports, ref = record.computation.filter_reports, csv_route[1].computation.filter_reports
    for i, reason in ((1, "max_distance"), (2, "rate_distance")):
        rep, ref_rep = reports[f"module1_station{i}"], ref[f"module1_station{i}"]
        assert rep.reasons[0][0] == reason and rep.removed[reason] == 1 + ref_rep.removed[reason]
        assert rep.n_kept == ref_rep.n_kept == len(rows[i]) - ref_rep.n_removed
    gt, ref_gt = record.groundtruth, csv_route[1].groundtruth
    np.testing.assert_array_equal(gt.t, ref_gt.t)
    assert np.max(np.abs(gt.position - ref_gt.position)) <= 1e-9


# ------------------------------------------------------------------ the reader


def test_status_codes_removed_and_counted_by_reason(tmp_path):
    """Each non-zero status is removed and counted by its reason; the valid messages come out
    sorted by time whatever the order of reception, repeated times left to module 1."""
    t = 1.7e9 + np.array([0.0, 0.4, 0.8, 1.2, 1.6, 2.0, 2.4, 2.8, 3.2, 3.6])
    status = [0, 1, 0, 2, 3, 4, 0, 9, 3, 0]
    msgs = [(2, s, 0.5 + 0.01 * k, 1.4, 10.0 + k, tk, tk)
            for k, (s, tk) in enumerate(zip(status, t, strict=True))]
    msgs.append((2, 0, 0.6, 1.4, 30.0, t[6], t[6]))  # a repeated time, kept for module 1
    msgs = msgs[5:] + msgs[:5]  # received out of order
    bag = read_theodolite_bag(write_bag(tmp_path / "s.bag", True, msgs))
    assert bag.ids == (2,)
    assert bag.removed[2] == {"tilt_out_of_range": 1, "wrong_target_distance": 1,
                              "tracking_exception": 2, "distance_under_1m": 1,
                              "unknown_status": 1}
    assert list(bag.removed[2]) == list(INPUT_REASONS)
    obs = bag.observations[2]
    np.testing.assert_array_equal(obs.t, t[[0, 2, 6, 6, 9]])
    np.testing.assert_array_equal(obs.d, [10.0, 12.0, 16.0, 30.0, 19.0])
    assert np.all(obs.status == 0) and (obs.station, obs.prism) == ("2", "2")
    st = bag.station(2, station="B", prism="P", additive_constant=0.01)
    assert (st.station, st.prism, st.additive_constant) == ("B", "P", 0.01)
    np.testing.assert_allclose(st.distance, obs.d + 0.01)
    rep = bag.report({"B": 2})
    assert (rep.n_in, rep.n_kept, rep.n_removed) == (11, 5, 6)
    with pytest.raises(InputError, match=r"no message of theodolite_id 1 \(station A\); "
                                         r"theodolite ids there: 2"):
        bag.station(1, station="A", prism="1")


@pytest.mark.parametrize("size", [7, 6, 5])
def test_older_float64multiarray_layout(size, rows, tmp_path):
    """``[id, Hz, V, d, sec, nsec, status]`` on /theodolite_data, as the theodolite_listener node
    publishes it (or, without status, ``[id, Hz, V, d, sec, nsec]`` or ``[id, Hz, V, d, t]``),
    gives the prism files' observations, the messages with a non-zero status removed and
    counted; its corrections (``[sec, nsec, id, offset]`` on /theodolite_correction_timestamp)
    are read; there is one time, so no time to choose."""
    msgs = messages(rows, invalid=INVALID if size == 7 else ())
    path = write_bag(tmp_path / "old.bag", True, msgs, topic=OLD_TOPIC, msgtype=ARRAY,
                     array_size=size, corrections=corrections_of(rows),
                     correction_topic="/theodolite_correction_timestamp")
    bag = read_theodolite_bag(path)
    assert (bag.topic, bag.layout, bag.time) == (OLD_TOPIC, "Float64MultiArray", "array")
    assert bag.correction_topic == "/theodolite_correction_timestamp"
    for i, r in rows.items():
        o = bag.observations[i]
        np.testing.assert_array_equal(np.column_stack([o.t, o.d, o.v, o.hz]), r)
        assert bag.removed[i] == (INVALID_COUNTS if size == 7 else dict.fromkeys(INPUT_REASONS,
                                                                                  0))
        np.testing.assert_allclose(bag.time_corrections[i].offset_s,
                                   [CLOCK_OFFSET[i], CLOCK_OFFSET[i] + 1e-4], rtol=0, atol=1e-12)
    with pytest.raises(InputError, match="one time .* applies to TheodoliteCoordsStamped"):
        read_theodolite_bag(path, time="theodolite")
    bad = write_bag(tmp_path / "bad.bag", True, msgs[:3], topic=OLD_TOPIC, msgtype=ARRAY,
                    array_size=8)
    with pytest.raises(InputError, match=r"message 0: expected 7 values \[id, Hz, V, d, sec, "
                                         r"nsec, status\] .* got 8"):
        read_theodolite_bag(bad)


def test_time_stamp_selection(rows, tmp_path):
    """``header.stamp`` by default; ``theodolite_time`` when asked, in the reader and through
    ``[measurements] time``; a value that is neither is refused naming the key."""
    bag_path = write_bag(tmp_path / "t.bag", True, messages(rows))
    header = read_theodolite_bag(bag_path)
    theo = read_theodolite_bag(bag_path, time="theodolite")
    assert (header.time, theo.time) == ("header", "theodolite")
    for i, r in rows.items():
        np.testing.assert_array_equal(header.observations[i].t, r[:, 0])
        np.testing.assert_allclose(theo.observations[i].t, r[:, 0] + CLOCK_OFFSET[i],
                                   rtol=0, atol=1e-6)
        np.testing.assert_array_equal(theo.observations[i].d, r[:, 1])
        assert header.stamp_difference_s[i] == pytest.approx(CLOCK_OFFSET[i], abs=1e-6)
    data, _ = load_deployment(deployment(tmp_path, bag=bag_path, extra='time = "theodolite"'))
    np.testing.assert_allclose(data.observations[0].t, rows[1][:, 0] + CLOCK_OFFSET[1],
                               rtol=0, atol=1e-6)
    assert data.input_report.source["time"] == "theodolite"
    with pytest.raises(ConfigError, match=r"\[measurements\] time = 'gps' is not one of "
                                          r"'header', 'theodolite'"):
        load_config(deployment(tmp_path, bag=bag_path, extra='time = "gps"'))


def test_clock_corrections_topic(rows, tmp_path):
    """The corrections are read beside the measurements (a namespaced bag keeps its own), or
    from ``[measurements] correction_topic``; missing ones are said, never silently dropped;
    the stamps follow the node's convention (``header.stamp = theodolite_time - offset``)."""
    ns = "/warthog/theodolite_master"
    msgs = messages({1: rows[1][:30], 2: rows[2][:30]}, invalid=())
    corr = [c for c in corrections_of(rows) if c[0] in (1, 2)]
    spaced = write_bag(tmp_path / "ns.bag", True, msgs, topic=f"{ns}/theodolite_data",
                       corrections=corr, correction_topic=f"{ns}/theodolite_correction_timestamp")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bag = read_theodolite_bag(spaced, topic=f"{ns}/theodolite_data")
    assert bag.correction_topic == f"{ns}/theodolite_correction_timestamp"
    for i in (1, 2):
        assert len(bag.time_corrections[i]) == 2
        # the offset the stamps carry is the one the corrections announce, with their sign
        assert bag.stamp_difference_s[i] == pytest.approx(CLOCK_OFFSET[i], abs=1e-6)
        assert bag.stamp_difference_s[i] == pytest.approx(
            bag.time_corrections[i].offset_s[0], abs=1e-6)
    # measurements on the node's topic, corrections in a namespace: a warning names them
    apart = write_bag(tmp_path / "apart.bag", True, msgs, corrections=corr,
                      correction_topic=f"{ns}/theodolite_correction_timestamp")
    with pytest.warns(RtsgtWarning, match=rf"no clock corrections on '{CORRECTION_TOPIC}': the "
                      rf"bag has clock corrections on '{ns}/theodolite_correction_timestamp' "
                      r"\(name it with \[measurements\] correction_topic\)"):
        bag = read_theodolite_bag(apart)
    assert bag.time_corrections == {} and bag.correction_topic is None
    extra = f'correction_topic = "{ns}/theodolite_correction_timestamp"'
    stations = "".join(f'[[stations]]\nid = "{i}"\nprism = "{i}"\n\n' for i in (1, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        data, _ = load_deployment(deployment(tmp_path, bag=apart, extra=extra,
                                             stations=stations))
    src = data.input_report.source
    assert src["correction_topic"] == f"{ns}/theodolite_correction_timestamp"
    assert src["time_corrections"]["2"]["count"] == 2
    # none at all: said too
    bare = write_bag(tmp_path / "bare.bag", True, msgs)
    with pytest.warns(RtsgtWarning, match="the bag has no topic of clock corrections"):
        read_theodolite_bag(bare)
    # a topic given that is not in the bag, or not of corrections: one line naming it
    with pytest.raises(InputError, match=rf"^{apart}: \[measurements\] correction_topic "
                                         r"'/nope' is not in the bag; the bag has clock "
                                         rf"corrections on '{ns}/theodolite_correction_"):
        read_theodolite_bag(apart, correction_topic="/nope")
    with pytest.raises(InputError, match=rf"topic '{TOPIC}' has type {COORDS}, expected "):
        read_theodolite_bag(apart, correction_topic=TOPIC)


def test_ros2_bag_without_message_definitions(rows, tmp_path):
    """A ROS 2 bag recorded before Iron carries no definitions: the registered types read it."""
    path = write_bag(tmp_path / "old_ros2", False, messages({1: rows[1][:20]}, invalid=()))
    (db,) = path.glob("*.db3")
    with sqlite3.connect(db) as con:
        con.execute("DELETE FROM message_definitions")
    obs = read_theodolite_bag(path).observations[1]
    np.testing.assert_array_equal(np.column_stack([obs.t, obs.d, obs.v, obs.hz]), rows[1][:20])


def test_theodolite_ids_mapped_to_stations(rows, tmp_path):
    """``theodolite_id`` says which messages are which station's (default: the same number)."""
    bag = write_bag(tmp_path / "m.bag", True, messages(rows, invalid=()))
    stations = "".join(f'[[stations]]\nid = "{s}"\nprism = "{s}"\ntheodolite_id = {i}\n\n'
                       for s, i in ((1, 3), (2, 1), (3, 2)))
    data, _ = load_deployment(deployment(tmp_path, bag=bag, stations=stations))
    for obs, i in zip(data.observations, (3, 1, 2), strict=True):
        np.testing.assert_array_equal(obs.t, rows[i][:, 0])
    assert [(o.station, o.prism) for o in data.observations] == [("1", "1"), ("2", "2"),
                                                                ("3", "3")]
    assert data.input_report.source["theodolite_ids"] == {"1": 3, "2": 1, "3": 2}
    default = load_config(deployment(tmp_path, bag=bag))
    assert [s.theodolite_id for s in default.stations] == [1, 2, 3]


# ------------------------------------------------------------------ bad input


def test_bag_without_the_topic_is_one_line_naming_it(rows, tmp_path):
    path = write_bag(tmp_path / "other.bag", True, messages({1: rows[1][:5]}, invalid=()),
                     topic="/something_else")
    with pytest.raises(InputError) as info:
        read_theodolite_bag(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: no total-station measurements: expected topic '{TOPIC}'")
    assert "/something_else (theodolite_node_msgs/msg/TheodoliteCoordsStamped)" in msg
    with pytest.raises(InputError, match=f"^{path}: topic '/nope' is not in the bag; topics"):
        read_theodolite_bag(path, topic="/nope")
    result = runner.invoke(app, ["run", str(deployment(tmp_path, bag=path)), "-o",
                                 str(tmp_path / "out"), "-q"])
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: no total-station")
    assert "Traceback" not in result.output and not (tmp_path / "out").exists()


def test_wrong_message_type_is_one_line_naming_the_topic(rows, tmp_path):
    path = write_bag(tmp_path / "pose", False, messages({1: rows[1][:5]}, invalid=()),
                     msgtype="geometry_msgs/msg/PoseStamped")
    with pytest.raises(InputError, match=f"^{path}: topic '{TOPIC}' has type "
                                         "geometry_msgs/msg/PoseStamped, expected "):
        read_theodolite_bag(path)
    result = runner.invoke(app, ["run", str(deployment(tmp_path, bag=path)), "-o",
                                 str(tmp_path / "out"), "-q"])
    assert result.exit_code == 1 and len(result.stderr.strip().splitlines()) == 1
    assert f"topic '{TOPIC}' has type geometry_msgs/msg/PoseStamped" in result.stderr
    assert "Traceback" not in result.output


def test_impossible_values_of_a_valid_message_name_it(rows, tmp_path):
    msgs = messages({3: rows[3][:6]}, invalid=())
    msgs[4] = (*msgs[4][:4], -2.5, *msgs[4][5:])
    path = write_bag(tmp_path / "neg.bag", True, msgs)
    with pytest.raises(InputError, match=rf"^{path}: topic '{TOPIC}', message 4 \(theodolite_id "
                                         r"3, status 0\): expected a positive slope distance, "
                                         r"got -2.5 m"):
        read_theodolite_bag(path)
    msgs = messages({3: rows[3][:6]}, invalid=())
    msgs[2] = (*msgs[2][:3], 90.0, *msgs[2][4:])  # a zenith angle in degrees
    with pytest.raises(InputError, match=r"message 2 .* zenith angle \(elevation\) in \(0, pi\)"):
        read_theodolite_bag(write_bag(tmp_path / "deg.bag", True, msgs))


def test_configuration_errors(rows, tmp_path):
    bag = write_bag(tmp_path / "c.bag", True, messages({1: rows[1][:5]}, invalid=()))
    both = '[[stations]]\nid = "1"\nprism = "1"\nfile = "x.csv"\n\n'
    with pytest.raises(ConfigError, match=r"\[stations #1\] file: the measurements come from "
                                          r"\[measurements\] file c.bag; give"):
        load_config(deployment(tmp_path, bag=bag, stations=both))
    named = '[[stations]]\nid = "a"\nprism = "1"\n\n'
    with pytest.raises(ConfigError, match=r"id = 'a' is not a theodolite number: give "
                                          "theodolite_id"):
        load_config(deployment(tmp_path, bag=bag, stations=named))
    twice = "".join(f'[[stations]]\nid = "{i}"\nprism = "{i}"\ntheodolite_id = 1\n\n'
                    for i in (1, 2))
    with pytest.raises(ConfigError, match=r"duplicated theodolite_id in \[\[stations\]\]"):
        load_config(deployment(tmp_path, bag=bag, stations=twice))
    stray = (f'[[stations]]\nid = "1"\nprism = "1"\nfile = "{EXCERPT / "prism1.csv"}"\n'
             'theodolite_id = 1\n\n')
    with pytest.raises(ConfigError, match=r"theodolite_id applies to measurements from a bag"):
        load_config(deployment(tmp_path, rows=rows, stations=stray))
    with pytest.raises(ConfigError, match=r"\[measurements\] file = .*: no such file"):
        load_config(deployment(tmp_path, bag=tmp_path / "missing.bag"))
    absent = load_config(deployment(tmp_path, bag=bag))  # station 2 has no message in the bag
    with pytest.raises(InputError, match=r"no message of theodolite_id 2 \(station 2\); "
                                         r"theodolite ids there: 1"):
        load_deployment(absent)
