"""Readers of position-only ground truths (rtsgt.io.positions): the forms public datasets
give a tracked prism in (rtsgt CSV, EuRoC ``leica0/data.csv``, ``rostopic echo -p`` tables,
``PointStamped`` / ``PoseStamped`` / ... topics of ROS 1 and ROS 2 bags), on files the tests
write (bags by rosbags' writers, as a ROS driver would)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rtsgt.errors import InputError
from rtsgt.io.positions import (
    list_position_topics,
    position_csv_form,
    read_position_bag,
    read_position_csv,
    read_positions,
    write_position_csv,
)
from rtsgt.types import PositionTrajectory

T0 = 1_668_095_037.0


def _track(n=50, cov=True, seed=0):
    rng = np.random.default_rng(seed)
    t = T0 + 0.2 * np.arange(n) + rng.uniform(0, 0.01, n)
    p = np.c_[np.cos(t - T0), np.sin(t - T0), 0.1 * (t - T0)] * 10 + rng.normal(size=(n, 3))
    C = None
    if cov:
        A = rng.normal(size=(n, 3, 3)) * 1e-3
        C = A @ np.swapaxes(A, 1, 2) + np.eye(3) * 1e-8
    return PositionTrajectory(t, p, C, "prism")


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_rtsgt_form_round_trip(tmp_path):
    for cov in (True, False):
        tr = _track(cov=cov)
        write_position_csv(tmp_path / "p.csv", tr)
        back = read_position_csv(tmp_path / "p.csv")
        np.testing.assert_array_equal(back.t, tr.t)
        np.testing.assert_array_equal(back.position, tr.position)
        if cov:
            np.testing.assert_array_equal(back.cov, tr.cov)
        else:
            assert back.cov is None
        assert position_csv_form(tmp_path / "p.csv") == "rtsgt"
        assert back.name == "p.csv"


def test_headerless_and_extra_columns(tmp_path):
    tr = _track(5, cov=False)
    rows = "".join(f"{t!r} {x!r} {y!r} {z!r}\n" for t, (x, y, z) in zip(
        tr.t.tolist(), tr.position.tolist(), strict=True))
    back = read_position_csv(_write(tmp_path, "bare.txt", rows))
    np.testing.assert_array_equal(back.position, tr.position)
    assert position_csv_form(tmp_path / "bare.txt") is None  # no header: not auto-detected
    back = read_position_csv(_write(tmp_path, "commented.txt", "# t x y z\n" + rows))
    np.testing.assert_array_equal(back.t, tr.t)
    text = "T,X,Y,Z,quality\n" + "".join(
        f"{t!r},{x!r},{y!r},{z!r},3\n" for t, (x, y, z) in zip(tr.t.tolist(),
                                                                 tr.position.tolist(),
                                                                 strict=True))
    back = read_position_csv(_write(tmp_path, "extra.csv", text))
    np.testing.assert_array_equal(back.t, tr.t)


def test_euroc_leica_form(tmp_path):
    """EuRoC's leica0/data.csv: integer nanoseconds, the header a '#' line."""
    ns = np.array([1403715523912143104, 1403715524012143104, 1403715524112143104])
    text = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]\n" + "".join(
        f"{n},{0.1 * k},{-0.2 * k},{1.0 + k}\n" for k, n in enumerate(ns))
    path = _write(tmp_path, "data.csv", text)
    assert position_csv_form(path) == "euroc"
    tr = read_positions(path)
    np.testing.assert_allclose(tr.t - 1403715523.0, [0.912143104, 1.012143104, 1.112143104],
                               atol=3e-7)  # float64 at 1.4e9 s: 2.4e-7 s
    np.testing.assert_allclose(tr.position[2], [0.2, -0.4, 3.0])
    assert tr.cov is None


def test_rostopic_forms(tmp_path):
    """``rostopic echo -p``: PointStamped, PoseStamped (NTU VIRAL's leica_pose.csv layout) and
    PoseWithCovarianceStamped (the position block of its covariance); the header stamp, or
    %time when every stamp is zero."""
    stamps = [1_636_000_000_100_000_000 + k * 100_000_000 for k in range(3)]
    point = "%time,field.header.seq,field.header.stamp,field.header.frame_id,field.point.x," \
            "field.point.y,field.point.z\n" + "".join(
                f"{s + 5000},{k},{s},world,{k}.5,{-k},{2 * k}\n" for k, s in enumerate(stamps))
    tr = read_position_csv(_write(tmp_path, "point.csv", point))
    np.testing.assert_allclose(tr.t - 1_636_000_000, [0.1, 0.2, 0.3], atol=3e-7)
    np.testing.assert_allclose(tr.position[1], [1.5, -1.0, 2.0])
    pose = ("%time,field.header.seq,field.header.stamp,field.header.frame_id,"
            "field.pose.position.x,field.pose.position.y,field.pose.position.z,"
            "field.pose.orientation.x,field.pose.orientation.y,field.pose.orientation.z,"
            "field.pose.orientation.w\n") + "".join(
                f"{s},{k},0,leica,{k},{k},{k},0,0,0,0\n" for k, s in enumerate(stamps))
    path = _write(tmp_path, "leica_pose.csv", pose)
    assert position_csv_form(path) == "rostopic"
    tr = read_position_csv(path)
    np.testing.assert_allclose(tr.t - 1_636_000_000, [0.1, 0.2, 0.3], atol=3e-7)  # %time
    cov = np.diag([1e-6, 4e-6, 9e-6, 1, 1, 1]).ravel()
    names = ",".join(f"field.pose.covariance{i}" for i in range(36))
    posecov = ("%time,field.header.stamp,field.pose.pose.position.x,field.pose.pose.position.y,"
               f"field.pose.pose.position.z,{names}\n") + "".join(
                   f"{s},{s},{k},0,0," + ",".join(map(repr, cov.tolist())) + "\n"
                   for k, s in enumerate(stamps))
    tr = read_position_csv(_write(tmp_path, "posecov.csv", posecov))
    np.testing.assert_allclose(tr.cov[0], np.diag([1e-6, 4e-6, 9e-6]))


@pytest.mark.parametrize("text, match", [
    ("", "empty file"),
    ("t,x,y,z\n", "no data line"),
    ("t,x,y,z,cov_xx\n1,0,0,0,1\n", "missing cov_xy"),
    ("t,x,y,z\n2,0,0,0\n1,0,0,0\n", "increas"),
    ("t,x,y,z\n1,0,a,0\n", "y"),
    ("t,x,y,z\n1,0,nan,0\n", "NaN|finite"),
    ("t,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz\n1,0,0,0,1,2,0,1,0,1\n",
     "positive semi-definite"),
    ("time,east,north\n1,0,0\n", "unknown position CSV header"),
    ("t,x,y,z\n1668095037000,0,0,0\n", "ms|milli"),
])
def test_csv_errors_name_the_file_and_line(tmp_path, text, match):
    path = _write(tmp_path, "bad.csv", text)
    with pytest.raises(InputError, match=match) as exc:
        read_position_csv(path)
    assert "bad.csv" in str(exc.value)


rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

TYPES = {
    "point": "geometry_msgs/msg/PointStamped",
    "pose": "geometry_msgs/msg/PoseStamped",
    "posecov": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "odom": "nav_msgs/msg/Odometry",
    "tfs": "geometry_msgs/msg/TransformStamped",
}


def _messages(ts, ros1, tr: PositionTrajectory, kind, order):
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Point, Quat, Vec = (T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"],
                        T["geometry_msgs/msg/Vector3"])
    Pose, PoseCov = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/PoseWithCovariance"]
    zero_q = Quat(x=0.0, y=0.0, z=0.0, w=0.0)  # a prism topic's meaningless orientation
    for k in order:
        sec = int(tr.t[k])
        stamp = Time(sec=sec, nanosec=int(round((tr.t[k] - sec) * 1e9)))
        header = (Header(seq=int(k), stamp=stamp, frame_id="leica") if ros1
                  else Header(stamp=stamp, frame_id="leica"))
        x, y, z = (float(v) for v in tr.position[k])
        cov = np.zeros((6, 6))
        if tr.cov is not None:
            cov[:3, :3] = tr.cov[k]
            cov[3:, 3:] = np.eye(3)
        if kind == "point":
            msg = T[TYPES[kind]](header=header, point=Point(x=x, y=y, z=z))
        elif kind == "pose":
            msg = T[TYPES[kind]](header=header, pose=Pose(position=Point(x=x, y=y, z=z),
                                                          orientation=zero_q))
        elif kind in ("posecov", "odom"):
            pc = PoseCov(pose=Pose(position=Point(x=x, y=y, z=z), orientation=zero_q),
                         covariance=cov.ravel())
            if kind == "posecov":
                msg = T[TYPES[kind]](header=header, pose=pc)
            else:
                TwistCov, Twist = T["geometry_msgs/msg/TwistWithCovariance"], \
                    T["geometry_msgs/msg/Twist"]
                tw = TwistCov(twist=Twist(linear=Vec(x=0.0, y=0.0, z=0.0),
                                          angular=Vec(x=0.0, y=0.0, z=0.0)),
                              covariance=np.zeros(36))
                msg = T[TYPES[kind]](header=header, child_frame_id="prism", pose=pc, twist=tw)
        else:
            Tr = T["geometry_msgs/msg/Transform"]
            msg = T[TYPES[kind]](header=header, child_frame_id="prism", transform=Tr(
                translation=Vec(x=x, y=y, z=z), rotation=Quat(x=0.0, y=0.0, z=0.0, w=1.0)))
        yield int(tr.t[k] * 1e9) + 1000, msg


def write_bag(path: Path, ros1: bool, tr: PositionTrajectory, order=None) -> Path:
    """One topic per message type, the messages in ``order`` (record times by stamp)."""
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    order = range(len(tr)) if order is None else order
    if ros1:
        writer = Writer1(path)
    else:
        try:
            writer = Writer2(path, version=8)
        except TypeError:  # rosbags < 0.10 has no version argument
            writer = Writer2(path)
    with writer as w:
        for kind, msgtype in TYPES.items():
            conn = w.add_connection(f"/leica/{kind}", msgtype, typestore=ts)
            for ns, msg in _messages(ts, ros1, tr, kind, order):
                raw = ts.serialize_ros1(msg, msgtype) if ros1 else ts.serialize_cdr(msg, msgtype)
                w.write(conn, ns, raw)
    return path


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def bag(request, tmp_path_factory):
    d = tmp_path_factory.mktemp(request.param)
    ros1 = request.param == "ros1"
    tr = _track(40)
    # out of order, with one message repeated: sorted, the repeat dropped
    order = [*range(20, 40), *range(0, 20), 5]
    return write_bag(d / ("leica.bag" if ros1 else "leica"), ros1, tr, order), tr


def test_every_position_topic_of_a_bag(bag):
    path, tr = bag
    assert set(list_position_topics(path)) == {f"/leica/{k}" for k in TYPES}
    for kind in TYPES:
        got = read_positions(path, topic=f"/leica/{kind}")
        np.testing.assert_allclose(got.t, tr.t, rtol=0, atol=2e-9)
        np.testing.assert_array_equal(got.position, tr.position)
        if kind in ("posecov", "odom"):
            np.testing.assert_array_equal(got.cov, tr.cov)
        else:
            assert got.cov is None


def test_bag_errors(bag, tmp_path):
    path, tr = bag
    with pytest.raises(InputError, match="position topics in the bag: /leica/odom"):
        read_position_bag(path, None)
    with pytest.raises(InputError, match="not in the bag"):
        read_position_bag(path, "/leica/none")
    with pytest.raises(InputError, match="not found"):
        read_position_bag(tmp_path / "missing.bag", "/leica/point")


def test_conflicting_duplicate_stamps_are_refused(tmp_path):
    tr = _track(6, cov=False)
    moved = PositionTrajectory(tr.t, tr.position + 1.0)
    path = tmp_path / "dup.bag"
    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer1(path) as w:
        conn = w.add_connection("/leica/point", TYPES["point"], typestore=ts)
        for src in (tr, moved):
            for ns, msg in _messages(ts, True, src, "point", [2]):
                w.write(conn, ns, ts.serialize_ros1(msg, TYPES["point"]))
    with pytest.raises(InputError, match="share the stamp"):
        read_position_bag(path, "/leica/point")


def test_cli_evaluates_against_a_prism_topic_and_a_position_csv(tmp_path):
    """``rtsgt evaluate BAG EST --gt-topic T --lever-arm l``: the estimate's point against a
    PointStamped topic (ROS 2), and the same positions as a EuRoC leica0 CSV."""
    import json

    from typer.testing import CliRunner

    from rtsgt.cli.main import app
    from rtsgt.io.trajectory import write_tum
    from test_evaluation_synth import smooth_truth, trajectory

    t, p, R = smooth_truth(300)
    lever = np.array([-0.2937, -0.0123, -0.2731])
    prism = PositionTrajectory(t, p + R @ lever)
    bag = write_bag(tmp_path / "gt", False, prism)
    write_tum(tmp_path / "est.tum", trajectory(t[::2], p[::2], R[::2]))
    runner = CliRunner()
    args = [str(tmp_path / "est.tum"), "--lever-arm", "-0.2937,-0.0123,-0.2731", "--json"]
    r = runner.invoke(app, ["evaluate", str(bag), *args, "--gt-topic", "/leica/point"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["ground_truth"] == "positions" and d["ape"]["translation_m"]["max"] < 1e-6
    assert d["nees"]["position"]["mean"] is None  # a PointStamped has no covariance
    ns = np.round(t * 1e9).astype(np.int64)
    text = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m]\n" + "".join(
        f"{n},{x!r},{y!r},{z!r}\n" for n, (x, y, z) in zip(ns.tolist(), prism.position.tolist(),
                                                           strict=True))
    csv = _write(tmp_path, "data.csv", text)
    r = runner.invoke(app, ["evaluate", str(csv), *args])  # told by its header
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["ape"]["translation_m"]["max"] < 1e-6
    r = runner.invoke(app, ["evaluate", str(bag), *args])
    assert r.exit_code == 1 and "/leica/point" in r.output  # the position topics listed
    # a mounting needs the ground truth's rotation: one line, no number
    r = runner.invoke(app, ["evaluate", str(csv), *args, "--estimate", "rotation"])
    assert r.exit_code == 1 and "position-only ground truth" in r.output
    assert "Traceback" not in r.output
