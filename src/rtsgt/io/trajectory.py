"""Readers and writers of pose trajectories: TUM, KITTI, EuRoC, rtsgt covariance CSV, ROS bags.

Every reader returns a :class:`~rtsgt.types.PoseTrajectory` (``T_world_body``, s, m,
scalar-last quaternions, optional 6x6 left-perturbation covariance x, y, z, rx, ry, rz) and
reports bad input as an :class:`~rtsgt.errors.InputError` naming the file and line;
:func:`detect_format` tells the formats apart. Formats, tolerances and detection:
docs/file-formats.md#trajectories.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Sequence
from os import PathLike
from pathlib import Path

import numpy as np

from rtsgt.choices import TRAJECTORY_FORMATS as FORMATS  # understood by read_trajectory
from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.io._bag import BAG_SUFFIXES, open_bag
from rtsgt.io._parse import (
    atomic_write_text,
    check_increasing,
    fmt_float,
    is_number,
    ns_to_seconds,
    numbered_lines,
    read_table,
    read_text,
    split_rows,
    table_text,
    to_float,
    to_int,
)
from rtsgt.types import PoseTrajectory

#: Tolerance on the norm of a quaternion (and the orthonormality of a rotation matrix).
UNIT_TOL = 1e-3

TUM_COLUMNS = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
#: The comment line :func:`write_tum` writes first (without the ``# ``).
TUM_COMMENT = "t[s] x[m] y[m] z[m] qx qy qz qw"
COV_COLUMNS = TUM_COLUMNS + tuple(f"cov_{i}{j}" for i in range(6) for j in range(6))
EUROC_COLUMNS = (
    "#timestamp [ns]",
    "p_RS_R_x [m]",
    "p_RS_R_y [m]",
    "p_RS_R_z [m]",
    "q_RS_w []",
    "q_RS_x []",
    "q_RS_y []",
    "q_RS_z []",
)
KITTI_COLUMNS = tuple(f"T{i}{j}" for i in range(3) for j in range(4))

#: Message types a bag topic may hold.
BAG_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
    "tf2_msgs/msg/TFMessage",
)


# --------------------------------------------------------------------------- validation


def _unit_quaternions(
    q: np.ndarray, numbers: Sequence[int], path, what: str = "quaternion"
) -> np.ndarray:
    """Renormalise quaternions within :data:`UNIT_TOL` of unit norm; error naming the line."""
    norm = np.linalg.norm(q, axis=1)
    bad = np.abs(norm - 1.0) > UNIT_TOL
    if np.any(bad):
        k = int(np.argmax(bad))
        raise InputError(
            f"{what} (qx, qy, qz, qw) = ({', '.join(f'{v:.6g}' for v in q[k])}) has norm "
            f"{norm[k]:.6g}, expected a unit quaternion (within {UNIT_TOL})",
            path,
            numbers[k],
        )
    return q / norm[:, None]


def _times_and_poses(path, numbers, t, p, q, cov=None) -> PoseTrajectory:
    check_increasing(t, numbers, path)
    return PoseTrajectory(t, p, q, cov)


def _data_lines(path, what: str) -> tuple[list[int], list[str]]:
    numbers, lines = numbered_lines(read_text(path))
    if not lines:
        raise InputError(f"empty file: expected {what}, found no data line", path)
    return numbers, lines


# --------------------------------------------------------------------------- TUM


def read_tum(path: str | PathLike) -> PoseTrajectory:
    """Read a TUM trajectory ``t x y z qx qy qz qw`` (s, m, scalar-last quaternion).

    Whitespace- or comma-separated (module docstring).

    Raises
    ------
    InputError
        Naming the file and line: wrong column count, non-number, NaN, non-unit quaternion,
        times not strictly increasing, empty file.
    """
    numbers, lines = _data_lines(path, "TUM poses 't x y z qx qy qz qw'")
    sep = "," if "," in lines[0] else None
    if sep and [c.strip().lower() for c in lines[0].split(",")] == list(TUM_COLUMNS):
        numbers, lines = numbers[1:], lines[1:]  # the header line of a comma-separated file
        if not lines:
            raise InputError("empty file: a header but no data line", path)
    tok = split_rows(lines, numbers, path, TUM_COLUMNS, sep)
    a = to_float(tok, numbers, path, TUM_COLUMNS)
    q = _unit_quaternions(a[:, 4:8], numbers, path)
    return _times_and_poses(path, numbers, a[:, 0], a[:, 1:4], q)


def write_tum(
    path: str | PathLike,
    traj: PoseTrajectory,
    *,
    decimals: tuple[int, int] | None = None,
    comment: str = TUM_COMMENT,
) -> None:
    """Write ``t x y z qx qy qz qw`` after a ``#`` comment line, atomically.

    Parameters
    ----------
    path : str or PathLike
    traj : PoseTrajectory
    decimals : (int, int), optional
        Fixed decimals of the times and positions, and of the quaternions (``rtsgt run``
        writes ``groundtruth.tum`` with (9, 12): ns, nm, 1e-12); None: the shortest text that
        reads back as the same float64.
    comment : str
        The comment line, without its ``# `` (default :data:`TUM_COMMENT`).
    """
    atomic_write_text(path, tum_text(traj, decimals=decimals, comment=comment))


def tum_text(traj: PoseTrajectory, *, decimals: tuple[int, int] | None = None,
             comment: str = TUM_COMMENT) -> str:
    """The text :func:`write_tum` writes (arguments as there)."""
    fmt = None if decimals is None else [f"%.{decimals[0]}f"] * 4 + [f"%.{decimals[1]}f"] * 4
    data = np.column_stack([traj.t, traj.position, traj.quat_xyzw])
    return table_text(data, header=f"# {comment}", sep=" ", fmt=fmt)


# --------------------------------------------------------------------------- KITTI


def _project_rotations(R: np.ndarray, numbers, path) -> np.ndarray:
    err = np.linalg.norm(R @ np.swapaxes(R, -1, -2) - np.eye(3), axis=(1, 2))
    det = np.linalg.det(R)
    bad = (err > UNIT_TOL) | (det <= 0)
    if np.any(bad):
        k = int(np.argmax(bad))
        raise InputError(
            f"the 3x3 block is not a rotation matrix (|R R^T - I| = {err[k]:.3g}, "
            f"det = {det[k]:.6g}); expected an orthonormal matrix within {UNIT_TOL}",
            path,
            numbers[k],
        )
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def read_kitti(
    path: str | PathLike, timestamps: str | PathLike | Sequence[float] | None
) -> PoseTrajectory:
    """Read KITTI poses (3x4 ``[R | t]`` row-major per line) with their timestamps.

    Parameters
    ----------
    path : str or PathLike
        The poses file.
    timestamps : str, PathLike or sequence of float
        A file with one time (s) per line, or the times themselves; one per pose.
    """
    if timestamps is None:
        raise InputError(
            "KITTI poses carry no time: give a timestamps file (one time in s per line, e.g. "
            "times.txt) with --timestamps",
            path,
        )
    numbers, lines = _data_lines(path, "KITTI poses (12 numbers per line)")
    tok = split_rows(lines, numbers, path, KITTI_COLUMNS, None)
    a = to_float(tok, numbers, path, KITTI_COLUMNS).reshape(-1, 3, 4)
    R = _project_rotations(a[:, :, :3], numbers, path)
    if isinstance(timestamps, (str, PathLike)):
        tnum, tlines = _data_lines(timestamps, "timestamps (one time in s per line)")
        ttok = split_rows(tlines, tnum, timestamps, ("t",), None)
        t = to_float(ttok, tnum, timestamps, ("t",))[:, 0]
        check_increasing(t, tnum, timestamps)
        tpath = timestamps
    else:
        t = np.asarray(timestamps, dtype=float)
        tnum, tpath = list(range(1, t.size + 1)), "timestamps"
        if not np.all(np.isfinite(t)):
            raise InputError("expected finite timestamps", tpath)
        check_increasing(t, tnum, tpath)
    if t.size != a.shape[0]:
        raise InputError(
            f"expected one timestamp per pose: {a.shape[0]} poses in {path}, {t.size} times", tpath
        )
    return PoseTrajectory(t, a[:, :, 3], matrix_to_quat_xyzw(R))


def write_kitti(
    path: str | PathLike, traj: PoseTrajectory, timestamps_path: str | PathLike | None = None
) -> None:
    """Write KITTI poses (and, when ``timestamps_path`` is given, the times), atomically."""
    T = np.concatenate([traj.rotation, traj.position[:, :, None]], axis=2).reshape(-1, 12)
    atomic_write_text(path, "".join(" ".join(fmt_float(v) for v in r) + "\n" for r in T.tolist()))
    if timestamps_path is not None:
        atomic_write_text(timestamps_path, "".join(fmt_float(v) + "\n" for v in traj.t.tolist()))


# --------------------------------------------------------------------------- EuRoC


def read_euroc(path: str | PathLike) -> PoseTrajectory:
    """Read an EuRoC CSV ``timestamp [ns], p x y z [m], q w x y z`` (w first; extra columns ok)."""
    numbers, lines = _data_lines(
        path, "EuRoC poses 'timestamp [ns], p_x, p_y, p_z, q_w, q_x, q_y, q_z'"
    )
    first = lines[0].split(",")
    if not is_number(first[0].strip()):  # a header without the leading '#'
        numbers, lines = numbers[1:], lines[1:]
        if not lines:
            raise InputError("empty file: a header but no data line", path)
    ncol = len(lines[0].split(","))
    if ncol < 8:
        raise InputError(
            f"expected at least 8 comma-separated columns ({', '.join(EUROC_COLUMNS)}), got {ncol}",
            path,
            numbers[0],
        )
    names = EUROC_COLUMNS + tuple(f"column {k + 1}" for k in range(8, ncol))
    tok = split_rows(lines, numbers, path, names, ",")
    ns = to_int(tok[:, :1], numbers, path, names[:1])[:, 0]
    t = ns_to_seconds(ns)
    a = to_float(tok[:, 1:8], numbers, path, names[1:8])
    q = _unit_quaternions(a[:, [4, 5, 6, 3]], numbers, path)
    return _times_and_poses(path, numbers, t, a[:, :3], q)


def write_euroc(path: str | PathLike, traj: PoseTrajectory) -> None:
    """Write an EuRoC pose CSV (integer ns, w first), atomically."""
    ns = np.round(traj.t * 1e9).astype(np.int64)
    lines = [",".join(EUROC_COLUMNS)]
    q = traj.quat_xyzw[:, [3, 0, 1, 2]]
    for k, (p, qq) in enumerate(zip(traj.position.tolist(), q.tolist(), strict=True)):
        lines.append(",".join([str(int(ns[k]))] + [fmt_float(v) for v in p + qq]))
    atomic_write_text(path, "\n".join(lines) + "\n")


# --------------------------------------------------------------------------- rtsgt covariance CSV


def read_covariance_csv(path: str | PathLike, *, run_file: bool = False) -> PoseTrajectory:
    """Read an rtsgt covariance CSV ``t,x,y,z,qx,qy,qz,qw,cov_00,...,cov_55`` (header optional, in
    that order; covariances finite, symmetric PSD to 1e-9). With ``run_file``, a table of a run
    directory read back exactly as written: the header required and columns found by name, NaN
    kept, no pose allowed, nothing checked or renormalised."""
    if run_file:
        header, data = read_table(path, COV_COLUMNS)
        a = data[:, [header.index(c) for c in COV_COLUMNS]]
        return PoseTrajectory(a[:, 0], a[:, 1:4], a[:, 4:8], a[:, 8:].reshape(-1, 6, 6))
    numbers, lines = _data_lines(path, "poses with covariance 't,x,y,z,qx,qy,qz,qw,cov_00..cov_55'")
    first = [c.strip() for c in lines[0].split(",")]
    if not is_number(first[0]):
        if [c.lower() for c in first] != list(COV_COLUMNS):
            raise InputError(
                f"expected the header {','.join(COV_COLUMNS[:9])},...,cov_55 "
                f"({len(COV_COLUMNS)} columns), got {','.join(first[:9])}... "
                f"({len(first)} columns)",
                path,
                numbers[0],
            )
        numbers, lines = numbers[1:], lines[1:]
        if not lines:
            raise InputError("empty file: a header but no data line", path)
    tok = split_rows(lines, numbers, path, COV_COLUMNS, ",")
    a = to_float(tok, numbers, path, COV_COLUMNS)
    q = _unit_quaternions(a[:, 4:8], numbers, path)
    cov = a[:, 8:].reshape(-1, 6, 6)
    scale = np.maximum(np.abs(cov).max(axis=(1, 2)), np.finfo(float).tiny)
    asym = np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2)) > 1e-9 * scale
    if np.any(asym):
        k = int(np.argmax(asym))
        raise InputError("the 6x6 covariance is not symmetric (cov_ij != cov_ji)", path, numbers[k])
    eig = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, 1, 2))).min(axis=1)
    neg = eig < -1e-9 * scale
    if np.any(neg):
        k = int(np.argmax(neg))
        raise InputError(
            f"the 6x6 covariance is not positive semi-definite (eigenvalue {eig[k]:.3g})",
            path,
            numbers[k],
        )
    return _times_and_poses(path, numbers, a[:, 0], a[:, 1:4], q, cov)


def write_covariance_csv(
    path: str | PathLike, traj: PoseTrajectory, *, digits: int | None = None
) -> None:
    """Write an rtsgt covariance CSV (header line, then one pose per line), atomically.

    Parameters
    ----------
    path : str or PathLike
    traj : PoseTrajectory
        With covariances.
    digits : int, optional
        Significant digits of every value (``rtsgt run`` writes
        ``groundtruth_covariance.csv`` with 17, ``%.17g``); None: the shortest text that reads
        back as the same float64.
    """
    if traj.cov is None:
        raise ValueError("Expected a trajectory with covariances")
    data = np.column_stack([traj.t, traj.position, traj.quat_xyzw, traj.cov.reshape(-1, 36)])
    fmt = None if digits is None else f"%.{digits}g"
    atomic_write_text(path, table_text(data, header=",".join(COV_COLUMNS), fmt=fmt))


def attach_covariance(
    traj: PoseTrajectory, cov_traj: PoseTrajectory, *, tol: float = 1e-6, source: str | None = None
) -> PoseTrajectory:
    """Give ``traj`` the covariances of ``cov_traj`` at the same times (within ``tol`` s).

    Raises
    ------
    InputError
        A pose of ``traj`` has no covariance at its time.
    """
    if cov_traj.cov is None:
        raise InputError("the covariance file holds no covariance", source)
    k = np.clip(np.searchsorted(cov_traj.t, traj.t), 1, max(len(cov_traj) - 1, 1))
    if len(cov_traj) == 1:
        k = np.zeros(len(traj), dtype=int)
        j = k
    else:
        left = np.abs(traj.t - cov_traj.t[k - 1]) <= np.abs(cov_traj.t[k] - traj.t)
        j = np.where(left, k - 1, k)
    bad = np.abs(cov_traj.t[j] - traj.t) > tol
    if np.any(bad):
        i = int(np.argmax(bad))
        raise InputError(
            f"no covariance at t = {traj.t[i]!r} s (pose {i} of the estimate); the covariance "
            f"file must hold every estimate time (within {tol} s)",
            source,
        )
    return PoseTrajectory(traj.t, traj.position, traj.quat_xyzw, cov_traj.cov[j])


# --------------------------------------------------------------------------- ROS bags


def _stamp(header) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def read_bag(
    path: str | PathLike, topic: str | None, *, child_frame: str | None = None
) -> PoseTrajectory:
    """Read a pose ``topic`` (a type of :data:`BAG_TYPES`) of a ROS 1 or ROS 2 bag; ``child_frame``
    selects the transform of ``TFMessage`` / ``TransformStamped`` / ``Odometry`` topics holding
    several. Any problem raises :class:`~rtsgt.errors.InputError` (an unknown topic lists the
    bag's topics)."""
    where = str(path)
    with open_bag(path) as reader:
        topics = {name: str(info.msgtype) for name, info in reader.topics.items()}
        listing = ", ".join(f"{n} ({t})" for n, t in sorted(topics.items())) or "none"
        if topic is None:
            usable = [n for n, t in sorted(topics.items()) if t in BAG_TYPES]
            raise InputError(
                "choose a topic with --topic; pose topics in the bag: "
                f"{', '.join(usable) or 'none'}"
                f" (all topics: {listing})",
                where,
            )
        if topic not in topics:
            raise InputError(
                f"topic {topic!r} is not in the bag; available topics: {listing}", where
            )
        msgtype = topics[topic]
        if msgtype not in BAG_TYPES:
            raise InputError(
                f"topic {topic!r} has type {msgtype}, expected one of {', '.join(BAG_TYPES)}", where
            )
        recs, covs = _bag_pose_records(reader, topic, msgtype)
    if not recs:
        raise InputError(f"topic {topic!r} holds no message", where)
    sel = _select_child(recs, topic, child_frame, where)
    stamps = np.array([recs[k][0] for k in sel])
    if np.all(stamps == 0):
        stamps = np.array([recs[k][1] for k in sel])
    p = np.array([recs[k][4] for k in sel], dtype=float)
    q = np.array([recs[k][5] for k in sel], dtype=float)
    cov = None if covs[sel[0]] is None else np.array([covs[k] for k in sel])
    labels = [f"message {k} (t = {stamps[i]!r})" for i, k in enumerate(sel)]
    finite = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(q), axis=1)
    if cov is not None:
        finite &= np.all(np.isfinite(cov), axis=(1, 2))
    if not np.all(finite):
        k = int(np.argmax(~finite))
        raise InputError(f"topic {topic!r}: NaN or infinite value in {labels[k]}", where)
    norm = np.linalg.norm(q, axis=1)
    bad = np.abs(norm - 1.0) > UNIT_TOL
    if np.any(bad):
        k = int(np.argmax(bad))
        raise InputError(
            f"topic {topic!r}: quaternion of norm {norm[k]:.6g} in {labels[k]}, expected a unit "
            f"quaternion (within {UNIT_TOL})",
            where,
        )
    q = q / norm[:, None]
    order = np.argsort(stamps, kind="stable")
    stamps, p, q = stamps[order], p[order], q[order]
    cov = None if cov is None else cov[order]
    same = np.flatnonzero(np.diff(stamps) == 0)
    if same.size:
        dup_ok = np.all(p[same] == p[same + 1], axis=1) & np.all(q[same] == q[same + 1], axis=1)
        if not np.all(dup_ok):
            k = int(same[np.argmax(~dup_ok)])
            raise InputError(
                f"topic {topic!r}: two different poses share the stamp t = {stamps[k]!r} s", where
            )
        keep = np.ones(stamps.size, dtype=bool)
        keep[same + 1] = False
        stamps, p, q = stamps[keep], p[keep], q[keep]
        cov = None if cov is None else cov[keep]
    if cov is not None and not np.any(cov):
        cov = None
    return PoseTrajectory(stamps, p, q, cov)


def _bag_pose_records(reader, topic: str, msgtype: str) -> tuple[list, list]:
    """Every pose of ``topic`` in bag order: ``(stamp, record time, child frame, parent frame,
    position, quaternion xyzw)`` and its 6x6 covariance (None where the type has none)."""
    conns = [c for c in reader.connections if c.topic == topic]
    recs: list[tuple[float, float, str, str, list[float], list[float]]] = []
    covs: list[np.ndarray] = []
    for conn, bag_ns, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        if msgtype == "tf2_msgs/msg/TFMessage":
            items = list(msg.transforms)
        else:
            items = [msg]
        for m in items:
            if msgtype in ("tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped"):
                tr = m.transform
                pos, rot, child = tr.translation, tr.rotation, str(m.child_frame_id)
                cov = None
            elif msgtype == "geometry_msgs/msg/PoseStamped":
                pos, rot, child, cov = m.pose.position, m.pose.orientation, "", None
            else:
                pos, rot = m.pose.pose.position, m.pose.pose.orientation
                child = str(getattr(m, "child_frame_id", ""))
                cov = np.asarray(m.pose.covariance, dtype=float).reshape(6, 6)
            recs.append(
                (
                    _stamp(m.header),
                    bag_ns * 1e-9,
                    child,
                    str(m.header.frame_id),
                    [pos.x, pos.y, pos.z],
                    [rot.x, rot.y, rot.z, rot.w],
                )
            )
            covs.append(cov)
    return recs, covs


def _select_child(recs: list, topic: str, child_frame: str | None, where: str) -> list[int]:
    """The records of ``child_frame``, or all when the topic has one child frame."""
    children = sorted({r[2] for r in recs})
    frames = sorted({(r[2], r[3]) for r in recs})
    if child_frame is not None:
        if child_frame not in children:
            avail = ", ".join(f"{c} (parent {p})" for c, p in frames)
            raise InputError(
                f"child frame {child_frame!r} not on topic {topic!r}; available: {avail}", where
            )
        sel = [k for k, r in enumerate(recs) if r[2] == child_frame]
    elif len(children) > 1:
        avail = ", ".join(f"{c} (parent {p})" for c, p in frames)
        raise InputError(
            f"topic {topic!r} holds several child frames; choose one with --child-frame: {avail}",
            where,
        )
    else:
        sel = list(range(len(recs)))
    return sel


# --------------------------------------------------------------------------- dispatch


def _quaternion_order(names: Sequence[str]) -> str | None:
    """``"tum"`` when column names put ``qw`` last (of 8), ``"euroc"`` when fifth, else None."""
    key = [re.sub(r"\[.*?\]|[^a-z]", "", n.lower()) for n in names]

    def is_w(k: str) -> bool:
        return k == "w" or (k.startswith("q") and k.endswith("w"))

    if len(key) >= 8 and is_w(key[4]):
        return "euroc"
    if len(key) == 8 and is_w(key[7]):
        return "tum"
    return None


def _comma_format(text: str, lines: Sequence[str], p: Path) -> str:
    """``"tum"`` or ``"euroc"`` for a comma-separated file of 8 or more columns that is not an
    rtsgt CSV (docs/file-formats.md#trajectories: a header decides, else the time stamps)."""
    first = [c.strip() for c in lines[0].split(",")]
    header = None
    if not is_number(first[0]):
        header, lines = first, lines[1:]
    else:  # the '#' comment line just before the first data line, if any
        before = text.split(lines[0], 1)[0].splitlines()
        comment = before[-1].strip() if before else ""
        if comment.startswith("#") and comment.count(",") >= 7:
            header = [c.strip() for c in comment.lstrip("#").split(",")]
    order = None if header is None else _quaternion_order(header)
    if order is not None:
        return order
    if len(first) != 8 or not lines:
        return "euroc"
    stamps = [line.split(",", 1)[0].strip() for line in lines[:200]]
    try:
        ints = np.array([int(v) for v in stamps], dtype=np.int64)
    except ValueError:
        why = f"a time stamp {stamps[0]!r} that is not integer nanoseconds"
    else:
        steps = np.diff(ints)
        if steps.size == 0 or np.median(steps) >= 1000:
            return "euroc"
        why = (f"integer time stamps {int(np.median(steps))} apart (a pose rate above 1 MHz "
               "if they were nanoseconds)")
    warnings.warn(
        f"{p}: comma-separated, 8 columns and {why}: read as TUM (t [s], x, y, z, qx, qy, qz, "
        "qw: qw last), not EuRoC (t [ns], x, y, z, qw, qx, qy, qz); give --format euroc if "
        "it is EuRoC",
        RtsgtWarning,
        stacklevel=3,
    )
    return "tum"


def detect_format(path: str | PathLike) -> str:
    """Guess the format of a trajectory file from its extension and first data lines.

    A comma-separated file of 8 columns is EuRoC or a comma-separated TUM file (module
    docstring); a guess of TUM from the time stamps comes with a
    :class:`~rtsgt.errors.RtsgtWarning`.
    """
    p = Path(path)
    if p.is_dir() or p.suffix in BAG_SUFFIXES:
        return "bag"
    if not p.exists():
        raise InputError("file not found", p)
    text = read_text(p)
    numbers, lines = numbered_lines(text)
    if not lines:
        raise InputError("empty file: no data line to recognise the format from", p)
    first = lines[0]
    if "," in first:
        head = [c.strip().lower() for c in first.split(",")]
        if head == list(TUM_COLUMNS):
            return "tum"
        if head[:8] == list(TUM_COLUMNS) or len(head) == len(COV_COLUMNS):
            return "rtsgt"
        if len(head) >= 8:
            return _comma_format(text, lines, p)
    ncol = len(first.split())
    if ncol == 8:
        return "tum"
    if ncol == 12:
        return "kitti"
    raise InputError(
        f"cannot recognise the trajectory format ({ncol} columns on line {numbers[0]}); "
        f"give --format ({'|'.join(FORMATS)})",
        p,
    )


def read_trajectory(
    path: str | PathLike,
    fmt: str | None = None,
    *,
    topic: str | None = None,
    timestamps: str | PathLike | None = None,
    child_frame: str | None = None,
) -> PoseTrajectory:
    """Read a trajectory in a format of :data:`FORMATS` (detected when ``fmt`` is None)."""
    fmt = detect_format(path) if fmt is None else fmt
    if fmt == "tum":
        return read_tum(path)
    if fmt == "kitti":
        return read_kitti(path, timestamps)
    if fmt == "euroc":
        return read_euroc(path)
    if fmt == "rtsgt":
        return read_covariance_csv(path)
    if fmt == "bag":
        return read_bag(path, topic, child_frame=child_frame)
    raise InputError(f"unknown trajectory format {fmt!r}; expected one of {', '.join(FORMATS)}")


def read_groundtruth_dir(directory: str | PathLike) -> PoseTrajectory:
    """Ground truth of an ``rtsgt run`` output directory.

    Reads ``groundtruth_covariance.csv`` (poses with their 6x6 covariances) when present,
    otherwise ``groundtruth.tum`` (poses only: no NEES, no noise floor).
    """
    d = Path(directory)
    if not d.is_dir():
        raise InputError("expected an rtsgt output directory", d)
    cov = d / "groundtruth_covariance.csv"
    if cov.is_file():
        return read_covariance_csv(cov)
    tum = d / "groundtruth.tum"
    if tum.is_file():
        return read_tum(tum)
    raise InputError(
        "no ground truth in this directory: expected groundtruth_covariance.csv or groundtruth.tum",
        d,
    )
