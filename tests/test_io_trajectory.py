"""Trajectory readers and writers: TUM, KITTI, EuRoC, rtsgt covariance CSV, ROS 1 / ROS 2 bags.

Round trips, cross-reads with evo's readers (an independent implementation of the formats),
bags written with ``rosbags`` itself for every supported message type, and the errors on bad
input (file and line named).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.io.trajectory import (
    attach_covariance,
    detect_format,
    read_bag,
    read_covariance_csv,
    read_euroc,
    read_groundtruth_dir,
    read_kitti,
    read_trajectory,
    read_tum,
    write_covariance_csv,
    write_euroc,
    write_kitti,
    write_tum,
)
from rtsgt.types import PoseTrajectory
from test_evaluation_synth import random_covariances, smooth_truth, trajectory


@pytest.fixture(scope="module")
def traj():
    t, p, R = smooth_truth(50)
    cov = random_covariances(50, np.random.default_rng(0))
    return trajectory(t, p, R, cov)


def assert_same_poses(a: PoseTrajectory, b: PoseTrajectory, atol=1e-12, t_atol=0.0):
    np.testing.assert_allclose(a.t, b.t, rtol=0, atol=t_atol)
    np.testing.assert_allclose(a.position, b.position, atol=atol)
    np.testing.assert_allclose(a.rotation, b.rotation, atol=atol)


# ----------------------------------------------------------------------------- round trips


def test_round_trips_are_exact(traj, tmp_path):
    write_tum(tmp_path / "a.tum", traj)
    t = read_tum(tmp_path / "a.tum")
    np.testing.assert_array_equal(t.t, traj.t)
    np.testing.assert_array_equal(t.position, traj.position)
    write_covariance_csv(tmp_path / "a.csv", traj)
    c = read_covariance_csv(tmp_path / "a.csv")
    np.testing.assert_array_equal(c.cov, traj.cov)
    np.testing.assert_array_equal(c.t, traj.t)
    write_kitti(tmp_path / "a.kitti", traj, tmp_path / "times.txt")
    k = read_kitti(tmp_path / "a.kitti", tmp_path / "times.txt")
    assert_same_poses(k, traj, atol=1e-14)
    write_euroc(tmp_path / "e.csv", traj)
    e = read_euroc(tmp_path / "e.csv")
    assert_same_poses(e, traj, atol=1e-14, t_atol=1e-6)  # integer ns
    for name, fmt in (
        ("a.tum", "tum"),
        ("a.csv", "rtsgt"),
        ("a.kitti", "kitti"),
        ("e.csv", "euroc"),
    ):
        assert detect_format(tmp_path / name) == fmt


def test_formats_agree_with_evo_readers(traj, tmp_path):
    """evo's own readers see the same poses in the files rtsgt writes (w-first EuRoC, 3x4
    KITTI rows, TUM xyzw)."""
    fi = pytest.importorskip("evo.tools.file_interface")
    write_tum(tmp_path / "a.tum", traj)
    write_kitti(tmp_path / "a.kitti", traj)
    write_euroc(tmp_path / "a.csv", traj)
    et = fi.read_tum_trajectory_file(str(tmp_path / "a.tum"))
    np.testing.assert_allclose(np.array(et.poses_se3)[:, :3, :3], traj.rotation, atol=1e-12)
    np.testing.assert_allclose(et.positions_xyz, traj.position, atol=0)
    ek = fi.read_kitti_poses_file(str(tmp_path / "a.kitti"))
    np.testing.assert_allclose(np.array(ek.poses_se3)[:, :3, :3], traj.rotation, atol=1e-12)
    ee = fi.read_euroc_csv_trajectory(str(tmp_path / "a.csv"))
    np.testing.assert_allclose(np.array(ee.poses_se3)[:, :3, :3], traj.rotation, atol=1e-12)
    np.testing.assert_allclose(ee.timestamps, traj.t, atol=1e-6)


def test_euroc_ground_truth_file_with_extra_columns_and_header(tmp_path):
    """A state_groundtruth_estimate0/data.csv line (17 columns, w first), from EuRoC MH_01."""
    text = (
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
        "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
        "b_w_RS_S_x [rad s^-1], "
        "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
        "b_a_RS_S_z [m s^-2]\n"
        "1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,"
        "-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n"
        "1403636580843555328,4.688177,-1.786770,0.787350,0.534640,-0.152996,-0.826976,-0.082443,"
        "-0.029272,0.033992,0.804599,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593\n"
    )
    (tmp_path / "data.csv").write_text(text)
    e = read_trajectory(tmp_path / "data.csv")
    assert e.t[0] == pytest.approx(1403636580.838555648, abs=1e-6)
    q = np.array([-0.153029, -0.827383, -0.082152, 0.534108])
    np.testing.assert_allclose(e.quat_xyzw[0], q / np.linalg.norm(q), atol=1e-12)
    np.testing.assert_allclose(e.position[1], [4.688177, -1.786770, 0.787350])


def test_groundtruth_dir_prefers_the_covariance_file(traj, tmp_path):
    write_tum(
        tmp_path / "groundtruth.tum", PoseTrajectory(traj.t, traj.position + 1.0, traj.quat_xyzw)
    )
    with pytest.raises(InputError, match="expected an rtsgt output directory"):
        read_groundtruth_dir(tmp_path / "x")
    g = read_groundtruth_dir(tmp_path)
    assert g.cov is None and g.position[0, 0] == pytest.approx(traj.position[0, 0] + 1.0)
    write_covariance_csv(tmp_path / "groundtruth_covariance.csv", traj)
    g = read_groundtruth_dir(tmp_path)
    np.testing.assert_array_equal(g.cov, traj.cov)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="groundtruth_covariance.csv or groundtruth.tum"):
        read_groundtruth_dir(tmp_path / "empty")


def test_writers_text_is_pinned(tmp_path):
    """The one TUM writer and the one covariance-CSV writer, in both styles: the shortest exact
    text (the default) and the fixed formats of ``rtsgt run`` (``groundtruth.tum`` with 9 and
    12 decimals, ``groundtruth_covariance.csv`` with 17 significant digits), byte for byte."""
    traj = PoseTrajectory(
        np.array([0.1, 1700000000.25]),
        np.array([[1.0, -2.5, 1e-3], [-0.0, 123.456789012345, 7.0]]),
        np.array([[0.0, 0.0, 0.0, 1.0], [0.5, -0.5, 0.5, 0.5]]),
        np.stack([np.eye(6) * 0.1, np.eye(6) * 2e-6]),
    )
    write_tum(tmp_path / "a.tum", traj)
    assert (tmp_path / "a.tum").read_text() == (
        "# t[s] x[m] y[m] z[m] qx qy qz qw\n"
        "0.1 1.0 -2.5 0.001 0.0 0.0 0.0 1.0\n"
        "1700000000.25 -0.0 123.456789012345 7.0 0.5 -0.5 0.5 0.5\n"
    )
    write_tum(tmp_path / "run.tum", traj, decimals=(9, 12), comment="t[s] x[m] (world)")
    assert (tmp_path / "run.tum").read_text() == (
        "# t[s] x[m] (world)\n"
        "0.100000000 1.000000000 -2.500000000 0.001000000 "
        "0.000000000000 0.000000000000 0.000000000000 1.000000000000\n"
        "1700000000.250000000 -0.000000000 123.456789012 7.000000000 "
        "0.500000000000 -0.500000000000 0.500000000000 0.500000000000\n"
    )

    def cov_text(diag: str, zero: str) -> str:
        return ",".join(diag if i == j else zero for i in range(6) for j in range(6))

    header = "t,x,y,z,qx,qy,qz,qw," + ",".join(f"cov_{i}{j}" for i in range(6) for j in range(6))
    write_covariance_csv(tmp_path / "a.csv", traj)
    assert (tmp_path / "a.csv").read_text() == (
        f"{header}\n"
        f"0.1,1.0,-2.5,0.001,0.0,0.0,0.0,1.0,{cov_text('0.1', '0.0')}\n"
        f"1700000000.25,-0.0,123.456789012345,7.0,0.5,-0.5,0.5,0.5,{cov_text('2e-06', '0.0')}\n"
    )
    write_covariance_csv(tmp_path / "run.csv", traj, digits=17)
    assert (tmp_path / "run.csv").read_text() == (
        f"{header}\n"
        "0.10000000000000001,1,-2.5,0.001,0,0,0,1,"
        f"{cov_text('0.10000000000000001', '0')}\n"
        "1700000000.25,-0,123.456789012345,7,0.5,-0.5,0.5,0.5,"
        f"{cov_text('1.9999999999999999e-06', '0')}\n"
    )
    for name in ("a.csv", "run.csv"):
        back = read_covariance_csv(tmp_path / name)
        np.testing.assert_array_equal(back.cov, traj.cov)
        np.testing.assert_array_equal(back.position, traj.position)


def test_run_file_reading_gives_back_what_the_run_wrote(tmp_path):
    """``run_file=True`` (what rtsgt.io.run_dir reads ``groundtruth_covariance.csv`` with):
    columns by name in any order, extra numeric columns ignored, NaN kept, no pose allowed,
    nothing renormalised; the header is required and a comment line is an error."""
    cols = ["t", "x", "y", "z", "qx", "qy", "qz", "qw"] + [
        f"cov_{i}{j}" for i in range(6) for j in range(6)
    ]
    vals = {c: 0.0 for c in cols} | {"t": 2.5, "x": float("nan"), "qw": 0.9999, "cov_01": 1e-3}
    order = ["extra"] + cols[::-1]
    row = ",".join("7" if c == "extra" else repr(vals[c]) for c in order)
    p = _write(tmp_path, "g.csv", ",".join(order) + "\n" + row + "\n")
    g = read_covariance_csv(p, run_file=True)
    assert g.t.tolist() == [2.5] and np.isnan(g.position[0, 0])
    assert g.quat_xyzw[0].tolist() == [0.0, 0.0, 0.0, 0.9999]  # not renormalised
    assert g.cov[0, 0, 1] == 1e-3 and g.cov[0, 1, 0] == 0.0  # not checked for symmetry
    empty = read_covariance_csv(_write(tmp_path, "e.csv", ",".join(cols) + "\n"), run_file=True)
    assert len(empty) == 0 and empty.cov.shape == (0, 6, 6)
    with pytest.raises(InputError, match=r"missing column\(s\) t, x,"):
        read_covariance_csv(_write(tmp_path, "n.csv", row + "\n"), run_file=True)
    with pytest.raises(InputError, match=r"c\.csv:2: expected 45 ,-separated columns") as exc:
        read_covariance_csv(_write(tmp_path, "c.csv", f"{','.join(order)}\n# x\n"), run_file=True)
    assert exc.value.line == 2


def test_attach_covariance(traj):
    sub = PoseTrajectory(traj.t[5:20], traj.position[5:20], traj.quat_xyzw[5:20])
    a = attach_covariance(sub, traj)
    np.testing.assert_array_equal(a.cov, traj.cov[5:20])
    shifted = PoseTrajectory(sub.t + 0.05, sub.position, sub.quat_xyzw)
    with pytest.raises(InputError, match="no covariance at t"):
        attach_covariance(shifted, traj)


# ----------------------------------------------------------------------------- bad files


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


GOOD = "1.0 0 0 0 0 0 0 1\n"


@pytest.mark.parametrize(
    ("text", "line", "match"),
    [
        (GOOD + "2.0 0 0 0 0 0 0.5 0.5\n", 2, "norm 0.707107, expected a unit quaternion"),
        ("# header\n" + GOOD + "2.0 0 nan 0 0 0 0 1\n", 3, "finite number in column 'y'"),
        (GOOD + "0.5 0 0 0 0 0 0 1\n", 2, "earlier than"),
        (GOOD + GOOD, 2, "duplicated timestamp"),
        (GOOD + "2.0 0 0 0 0 0 1\n", 2, "expected 8 whitespace-separated columns"),
        (GOOD + "2.0 0 0 x 0 0 0 1\n", 2, "column 'z'"),
    ],
)
def test_tum_errors_name_the_line(tmp_path, text, line, match):
    p = _write(tmp_path, "bad.tum", text)
    with pytest.raises(InputError, match=match) as exc:
        read_tum(p)
    assert exc.value.line == line and exc.value.path == str(p)


def test_quaternions_within_tolerance_are_renormalised(tmp_path):
    p = _write(tmp_path, "ok.tum", "1.0 0 0 0 0 0 0 1.0004\n2 0 0 0 0 0 0.6 0.8\n")
    np.testing.assert_allclose(np.linalg.norm(read_tum(p).quat_xyzw, axis=1), 1.0, atol=1e-15)


def test_other_bad_files(tmp_path, traj):
    with pytest.raises(InputError, match="empty file"):
        read_tum(_write(tmp_path, "e.tum", "# nothing\n\n"))
    with pytest.raises(InputError, match="file not found"):
        read_tum(tmp_path / "missing.tum")
    write_kitti(tmp_path / "k.txt", traj)
    with pytest.raises(InputError, match="timestamps file"):
        read_kitti(tmp_path / "k.txt", None)
    _write(tmp_path, "times.txt", "0\n1\n")
    with pytest.raises(InputError, match="one timestamp per pose"):
        read_kitti(tmp_path / "k.txt", tmp_path / "times.txt")
    with pytest.raises(InputError, match="not a rotation matrix") as exc:
        read_kitti(_write(tmp_path, "k2.txt", "1 0 0 0 0 2 0 0 0 0 1 0\n"), [0.0])
    assert exc.value.line == 1
    write_covariance_csv(tmp_path / "c.csv", traj)
    lines = (tmp_path / "c.csv").read_text().splitlines()
    vals = lines[3].split(",")
    vals[9] = str(float(vals[9]) + 1.0)  # cov_01 != cov_10
    lines[3] = ",".join(vals)
    with pytest.raises(InputError, match="not symmetric") as exc:
        read_covariance_csv(_write(tmp_path, "c2.csv", "\n".join(lines) + "\n"))
    assert exc.value.line == 4
    with pytest.raises(InputError, match="expected the header"):
        read_covariance_csv(_write(tmp_path, "c3.csv", "t,x,y\n" + "\n".join(lines[1:]) + "\n"))
    with pytest.raises(InputError, match="cannot recognise"):
        detect_format(_write(tmp_path, "w.txt", "1 2 3\n"))


# ----------------------------------------------------------------------------- misread units


TUM = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")


def _ns(t: np.ndarray) -> list[int]:
    """Integer nanoseconds of times in s (to the microsecond, exactly representable)."""
    return (np.round(t * 1e6).astype(np.int64) * 1000).tolist()


def _text(stamps: list, rows: list[list[float]], sep: str) -> str:
    """Lines ``stamp sep v1 sep v2 ...`` (shortest exact floats)."""
    return "".join(
        sep.join([str(a)] + [repr(v) for v in r]) + "\n" for a, r in zip(stamps, rows, strict=True)
    )


def test_nanosecond_stamps_in_seconds_formats_are_refused_naming_file_and_line(traj, tmp_path):
    """TUM, KITTI times and the rtsgt CSV are seconds: a stamp beyond 1e11 s (the year 5138)
    is refused, naming the file, the line, the value and the unit it looks like; EuRoC,
    documented as nanoseconds, reads the same stamps."""
    ns = _ns(traj.t)
    rows = np.column_stack([traj.position, traj.quat_xyzw]).tolist()
    tum = _text(ns, rows, " ")
    p = _write(tmp_path, "ns.tum", "# t[ns] x y z qx qy qz qw\n" + tum)
    with pytest.raises(InputError, match=r"too large for seconds.*looks like nanoseconds") as exc:
        read_trajectory(p)
    assert exc.value.path == str(p) and exc.value.line == 2
    assert f"{float(ns[0])!r}" in str(exc.value)
    write_kitti(tmp_path / "k.kitti", traj)
    _write(tmp_path, "times_ns.txt", "".join(f"{a}\n" for a in ns))
    with pytest.raises(InputError, match="nanoseconds") as exc:
        read_kitti(tmp_path / "k.kitti", tmp_path / "times_ns.txt")
    assert exc.value.path == str(tmp_path / "times_ns.txt") and exc.value.line == 1
    write_covariance_csv(tmp_path / "c.csv", traj)
    lines = (tmp_path / "c.csv").read_text().splitlines()
    for i, a in enumerate(ns, start=1):
        lines[i] = str(a) + lines[i][lines[i].index(","):]
    with pytest.raises(InputError, match="nanoseconds") as exc:
        read_covariance_csv(_write(tmp_path, "c_ns.csv", "\n".join(lines) + "\n"))
    assert exc.value.path == str(tmp_path / "c_ns.csv") and exc.value.line == 2
    write_euroc(tmp_path / "e.csv", traj)
    e = read_trajectory(tmp_path / "e.csv")
    np.testing.assert_allclose(e.t, traj.t, rtol=0, atol=1e-6)


def test_comma_separated_tum_is_not_taken_for_euroc(traj, tmp_path):
    """A comma-separated 't,x,y,z,qx,qy,qz,qw' file (seconds, qw last) is read as TUM, with a
    warning saying so; EuRoC (integer ns, qw first) stays EuRoC without a warning."""
    rows = np.column_stack([traj.t, traj.position, traj.quat_xyzw]).tolist()
    text = "".join(",".join(repr(v) for v in r) + "\n" for r in rows)
    p = _write(tmp_path, "comma.csv", text)
    with pytest.warns(RtsgtWarning, match="comma.csv: .*read as TUM") as rec:
        assert detect_format(p) == "tum"
    assert "qw last" in str(rec[0].message)
    with pytest.warns(RtsgtWarning, match="read as TUM"):
        got = read_trajectory(p)
    assert_same_poses(got, traj, atol=1e-15)
    np.testing.assert_array_equal(read_tum(p).quat_xyzw, got.quat_xyzw)  # --format tum
    # integer seconds (1 s apart: a pose rate of 1 GHz if they were nanoseconds)
    ints = "".join(f"{k}," + ",".join(repr(v) for v in r[1:]) + "\n" for k, r in enumerate(rows))
    with pytest.warns(RtsgtWarning, match="read as TUM"):
        got = read_trajectory(_write(tmp_path, "ints.csv", ints))
    np.testing.assert_array_equal(got.t, np.arange(len(rows)))
    np.testing.assert_array_equal(got.quat_xyzw[:, 3] > 0, traj.quat_xyzw[:, 3] > 0)
    # a header naming the TUM columns: TUM, no warning needed; EuRoC (with or without its
    # header comment) stays EuRoC, without a warning
    write_euroc(tmp_path / "e.csv", traj)
    bare = "".join((tmp_path / "e.csv").read_text().splitlines(keepends=True)[1:])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RtsgtWarning)
        h = read_trajectory(_write(tmp_path, "h.csv", ",".join(TUM) + "\n" + text))
        assert_same_poses(h, traj, atol=1e-15)
        for name in ("e.csv", "e_bare.csv"):
            if name == "e_bare.csv":
                _write(tmp_path, name, bare)
            assert detect_format(tmp_path / name) == "euroc"
            assert_same_poses(read_trajectory(tmp_path / name), traj, atol=1e-14, t_atol=1e-6)
        # integer-nanosecond rows whose header comment puts qw last: TUM (the header says so),
        # so the nanoseconds are refused instead of a silent w-first (EuRoC) reading
        ns = _ns(traj.t)
        qlast = _text(ns, [r[1:] for r in rows], ",")
        q = _write(tmp_path, "q.csv", "# t[ns], x, y, z, qx, qy, qz, qw\n" + qlast)
        assert detect_format(q) == "tum"
        with pytest.raises(InputError, match="nanoseconds") as exc:
            read_trajectory(q)
        assert exc.value.line == 2


# ----------------------------------------------------------------------------- bags

rosbags = pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

MSG_TYPES = {
    "pose": "geometry_msgs/msg/PoseStamped",
    "posecov": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "odom": "nav_msgs/msg/Odometry",
    "tfs": "geometry_msgs/msg/TransformStamped",
    "tf": "tf2_msgs/msg/TFMessage",
}


def _messages(ts, ros1: bool, traj: PoseTrajectory, kind: str):
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Point, Quat, Vec = (
        T["geometry_msgs/msg/Point"],
        T["geometry_msgs/msg/Quaternion"],
        T["geometry_msgs/msg/Vector3"],
    )
    Pose, PoseCov = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/PoseWithCovariance"]
    out = []
    for k in range(len(traj)):
        sec = int(traj.t[k])
        stamp = Time(sec=sec, nanosec=int(round((traj.t[k] - sec) * 1e9)))

        def header(frame="world", k=k, stamp=stamp):
            return (
                Header(seq=k, stamp=stamp, frame_id=frame)
                if ros1
                else Header(stamp=stamp, frame_id=frame)
            )

        x, y, z = traj.position[k]
        qx, qy, qz, qw = traj.quat_xyzw[k]
        pose = Pose(position=Point(x=x, y=y, z=z), orientation=Quat(x=qx, y=qy, z=qz, w=qw))
        cov = np.zeros(36) if traj.cov is None else traj.cov[k].reshape(36).copy()
        if kind == "pose":
            out.append(T[MSG_TYPES[kind]](header=header(), pose=pose))
        elif kind == "posecov":
            out.append(T[MSG_TYPES[kind]](header=header(), pose=PoseCov(pose=pose, covariance=cov)))
        elif kind == "odom":
            TwistCov, Twist = (
                T["geometry_msgs/msg/TwistWithCovariance"],
                T["geometry_msgs/msg/Twist"],
            )
            twist = TwistCov(
                twist=Twist(linear=Vec(x=0.0, y=0.0, z=0.0), angular=Vec(x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36),
            )
            out.append(
                T[MSG_TYPES[kind]](
                    header=header("odom"),
                    child_frame_id="base_link",
                    pose=PoseCov(pose=pose, covariance=cov),
                    twist=twist,
                )
            )
        else:
            TS, Tr = T["geometry_msgs/msg/TransformStamped"], T["geometry_msgs/msg/Transform"]
            tr = Tr(translation=Vec(x=x, y=y, z=z), rotation=Quat(x=qx, y=qy, z=qz, w=qw))
            base = TS(header=header("odom"), child_frame_id="base_link", transform=tr)
            if kind == "tfs":
                out.append(base)
            else:  # a second child frame in the same TF messages
                cam = TS(
                    header=header("base_link"),
                    child_frame_id="camera",
                    transform=Tr(
                        translation=Vec(x=0.1, y=0.0, z=0.2),
                        rotation=Quat(x=0.0, y=0.0, z=0.0, w=1.0),
                    ),
                )
                out.append(T[MSG_TYPES[kind]](transforms=[base, cam]))
    return out


def write_bag(path: Path, ros1: bool, traj: PoseTrajectory, kinds=tuple(MSG_TYPES)) -> Path:
    """A bag with one topic per message type (written by rosbags, as a ROS driver would)."""
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if MSG_TYPES["tf"] not in ts.types:  # the ROS 1 store lacks tf2_msgs
        ts.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", MSG_TYPES["tf"])
        )
    if ros1:
        writer = Writer1(path)
    else:
        try:
            writer = Writer2(path, version=8)
        except TypeError:  # rosbags < 0.10 has no version argument
            writer = Writer2(path)
    with writer as w:
        for kind in kinds:
            topic = "/tf" if kind == "tf" else f"/{kind}"
            conn = w.add_connection(topic, MSG_TYPES[kind], typestore=ts)
            for k, msg in enumerate(_messages(ts, ros1, traj, kind)):
                raw = (
                    ts.serialize_ros1(msg, MSG_TYPES[kind])
                    if ros1
                    else ts.serialize_cdr(msg, MSG_TYPES[kind])
                )
                w.write(conn, int(traj.t[k] * 1e9) + 1000, raw)
    return path


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def bag(request, traj, tmp_path_factory):
    d = tmp_path_factory.mktemp(request.param)
    ros1 = request.param == "ros1"
    return write_bag(d / ("poses.bag" if ros1 else "poses"), ros1, traj)


@pytest.mark.parametrize("kind", list(MSG_TYPES))
def test_bag_topics_read_back(bag, traj, kind):
    topic = "/tf" if kind == "tf" else f"/{kind}"
    child = "base_link" if kind == "tf" else None
    got = read_bag(bag, topic, child_frame=child)
    assert_same_poses(got, traj, atol=1e-12, t_atol=2e-6)
    if kind in ("posecov", "odom"):
        np.testing.assert_array_equal(got.cov, traj.cov)
    else:
        assert got.cov is None
    assert detect_format(bag) == "bag"


def test_bag_errors_list_what_is_available(bag):
    with pytest.raises(InputError, match="not in the bag; available topics:") as exc:
        read_bag(bag, "/nope")
    for name, typ in (("/pose", "PoseStamped"), ("/tf", "TFMessage"), ("/odom", "Odometry")):
        assert name in str(exc.value) and typ in str(exc.value)
    with pytest.raises(InputError, match="several child frames.*base_link.*camera"):
        read_bag(bag, "/tf")
    with pytest.raises(InputError, match="child frame 'lidar' not on topic"):
        read_bag(bag, "/tf", child_frame="lidar")
    with pytest.raises(InputError, match="--topic"):
        read_bag(bag, None)


def test_bag_written_by_evo_reads_back(traj, tmp_path):
    """evo's bag writer (PoseStamped, ROS 2) as an independent producer."""
    fi = pytest.importorskip("evo.tools.file_interface")
    from evo.core.trajectory import PoseTrajectory3D

    e = PoseTrajectory3D(traj.position.copy(), np.roll(traj.quat_xyzw, 1, axis=1), traj.t.copy())
    try:
        writer = Writer2(tmp_path / "evo_bag", version=8)
    except TypeError:
        writer = Writer2(tmp_path / "evo_bag")
    with writer as w:
        fi.write_bag_trajectory(w, e, "/est")
    got = read_bag(tmp_path / "evo_bag", "/est")
    assert_same_poses(got, traj, atol=1e-12, t_atol=2e-6)


def test_bag_nan_and_non_unit_quaternion(traj, tmp_path):
    p = traj.position.copy()
    p[3, 0] = np.nan
    write_bag(
        tmp_path / "nan.bag", True, PoseTrajectory(traj.t, p, traj.quat_xyzw), kinds=("pose",)
    )
    with pytest.raises(InputError, match="NaN.*message 3"):
        read_bag(tmp_path / "nan.bag", "/pose")
    q = traj.quat_xyzw.copy()
    q[7] *= 0.5
    write_bag(tmp_path / "q.bag", True, PoseTrajectory(traj.t, traj.position, q), kinds=("pose",))
    with pytest.raises(InputError, match="quaternion of norm 0.5 in message 7"):
        read_bag(tmp_path / "q.bag", "/pose")


def test_bag_out_of_order_and_duplicate_stamps(traj, tmp_path):
    """Messages are sorted by header stamp; an exact repeat is dropped, a conflicting one is an
    error naming the stamp."""
    order = np.r_[np.arange(10, 20), np.arange(0, 10), 5]  # out of order, pose 5 twice
    shuffled = PoseTrajectory(traj.t[order], traj.position[order], traj.quat_xyzw[order])
    write_bag(tmp_path / "s.bag", True, shuffled, kinds=("pose",))
    got = read_bag(tmp_path / "s.bag", "/pose")
    assert_same_poses(
        got, PoseTrajectory(traj.t[:20], traj.position[:20], traj.quat_xyzw[:20]), t_atol=2e-6
    )
    p = shuffled.position.copy()
    p[-1] += 0.1
    write_bag(
        tmp_path / "c.bag", True, PoseTrajectory(shuffled.t, p, shuffled.quat_xyzw), kinds=("pose",)
    )
    with pytest.raises(InputError, match="two different poses share the stamp"):
        read_bag(tmp_path / "c.bag", "/pose")


def test_missing_rosbags_gives_an_install_hint(monkeypatch, bag):
    import sys

    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(InputError, match=r"pip install 'rtsgt\[bags\]'"):
        read_bag(bag, "/pose")
