"""Readers and writer of position-only trajectories: a tracked prism as datasets give it.

Every reader returns a :class:`~rtsgt.types.PositionTrajectory` (s, m, optional 3x3
covariance, m^2) and reports bad input as an :class:`~rtsgt.errors.InputError` naming the file
and line. :func:`read_position_csv` tells its form by the header (rtsgt ``t,x,y,z[,cov_..]``,
EuRoC Leica, ``rostopic echo -p``); :func:`read_position_bag` reads a pose or point topic of a
ROS bag (the position only). docs/file-formats.md#position-ground-truth-files.
"""

from __future__ import annotations

from collections.abc import Sequence
from os import PathLike
from pathlib import Path

import numpy as np

from rtsgt.errors import InputError
from rtsgt.io._bag import BAG_SUFFIXES, open_bag
from rtsgt.io._parse import (
    atomic_write_text,
    check_increasing,
    fmt_float,
    is_number,
    ns_to_seconds,
    read_text,
    split_rows,
    to_float,
    to_int,
)
from rtsgt.types import PositionTrajectory

__all__ = ["POSITION_BAG_TYPES", "POSITION_COLUMNS", "POSITION_FORMATS", "list_position_topics",
           "position_csv_form", "read_position_bag", "read_position_csv", "read_positions",
           "write_position_csv"]

#: The columns of the rtsgt form: time, position, the upper triangle of the covariance.
POSITION_COLUMNS = ("t", "x", "y", "z")
COV_COLUMNS = ("cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")
#: Forms :func:`read_positions` understands.
POSITION_FORMATS = ("csv", "bag")
#: Message types of a position topic.
POSITION_BAG_TYPES = (
    "geometry_msgs/msg/PointStamped",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
)
#: ``rostopic echo -p`` position columns, by message layout (prefix before ``.x``).
_ROSTOPIC_POSITIONS = ("field.point", "field.pose.position", "field.pose.pose.position",
                       "field.transform.translation")

_IU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def _full_cov(upper: np.ndarray) -> np.ndarray:
    cov = np.empty((upper.shape[0], 3, 3))
    cov[:, _IU[0], _IU[1]] = upper
    cov[:, _IU[1], _IU[0]] = upper
    return cov


def _check_cov(cov: np.ndarray, path, numbers: Sequence[int] | None = None,
               labels: Sequence[str] | None = None) -> None:
    """Symmetric positive semi-definite within a relative 1e-9; the first bad one named (by
    its line ``numbers``, else its ``labels``)."""
    eig = np.linalg.eigvalsh(cov)
    scale = np.maximum(np.abs(eig).max(axis=1), np.finfo(float).tiny)
    bad = np.flatnonzero(eig[:, 0] < -1e-9 * scale)
    if bad.size:
        i = int(bad[0])
        what = "" if labels is None else f" in {labels[i]}"
        raise InputError(f"expected a symmetric positive semi-definite covariance (m^2){what}, "
                         f"got eigenvalues {', '.join(f'{e:.3g}' for e in eig[i])}", path,
                         None if numbers is None else numbers[i])


def _rows(text: str) -> tuple[list[int], list[str]]:
    """1-based numbers and contents of the non-blank lines (``#`` lines kept: a header)."""
    numbers, lines = [], []
    for i, line in enumerate(text.splitlines(), start=1):
        if line.strip():
            numbers.append(i)
            lines.append(line.strip())
    return numbers, lines


def position_csv_form(path: str | PathLike) -> str | None:
    """The form of a position CSV (``"rtsgt"``, ``"euroc"`` or ``"rostopic"``) told by its
    header line, or None when the file is none of them (a pose trajectory: TUM, EuRoC poses,
    an rtsgt covariance CSV). A file without a header is not recognised (give the kind of
    ground truth instead)."""
    p = Path(path)
    if not p.is_file():
        return None
    try:
        numbers, lines = _rows(read_text(p))
    except InputError:
        return None
    if not lines:
        return None
    first = lines[0].lstrip("#").strip()
    head = [c.strip() for c in (first.split(",") if "," in first else first.split())]
    names = [h.lstrip("#%").strip().lower() for h in head]
    if not head[0] or is_number(head[0]):
        return None
    if names[:4] == list(POSITION_COLUMNS) and (len(names) == 4 or names[4] == COV_COLUMNS[0]):
        return "rtsgt"
    if names[0].startswith("timestamp") and len(names) == 4:
        return "euroc"
    if any(f"{q}.x" in names for q in _ROSTOPIC_POSITIONS):
        return "rostopic"
    return None


def read_position_csv(path: str | PathLike, *, name: str | None = None) -> PositionTrajectory:
    """Read a position CSV in one of the forms of the module docstring.

    Parameters
    ----------
    path : str or PathLike
    name : str, optional
        What the point is (default: the file name).

    Raises
    ------
    InputError
        Naming the file and line (module docstring).
    """
    p = Path(path)
    numbers, lines = _rows(read_text(p))
    if not lines:
        raise InputError("empty file: expected positions 't,x,y,z', found no data line", p)
    label = p.name if name is None else name
    first = lines[0].lstrip("#").strip()  # a header may be a comment (EuRoC's '#timestamp')
    sep = "," if "," in first else None
    head = [c.strip() for c in (first.split(",") if sep else first.split())]
    if is_number(head[0]):  # no header: t x y z [cov_xx .. cov_zz], seconds
        body = [(k, ln) for k, ln in zip(numbers, lines, strict=True) if not ln.startswith("#")]
        nums, rows = [k for k, _ in body], [ln for _, ln in body]
        ncol = len(head)
        if ncol not in (4, 10):
            raise InputError(f"expected 4 columns (t x y z) or 10 (and the covariance "
                             f"cov_xx .. cov_zz) without a header line, got {ncol}", p,
                             numbers[0])
        cols = (*POSITION_COLUMNS, *COV_COLUMNS)[:ncol]
        tok = split_rows(rows, nums, p, cols, sep)
        return _rtsgt_form(p, nums, tok, list(cols), label)
    names = [h.lstrip("#%").strip().lower() for h in head]
    body = [(k, ln) for k, ln in zip(numbers[1:], lines[1:], strict=True)
            if not ln.startswith("#")]
    nums, rows = [k for k, _ in body], [ln for _, ln in body]
    if not rows:
        raise InputError("a header line but no data line", p, numbers[0])
    tok = split_rows(rows, nums, p, head, sep)
    if names[:4] == list(POSITION_COLUMNS):
        return _rtsgt_form(p, nums, tok, names, label)
    if names[0].startswith("timestamp"):
        return _euroc_form(p, nums, tok, names, label)
    if any(n.startswith("field.") for n in names):
        return _rostopic_form(p, nums, tok, names, label)
    raise InputError(f"unknown position CSV header {first!r}: expected 't,x,y,z[,cov_xx,..]', "
                     "EuRoC's '#timestamp [ns],p_x [m],..' or 'rostopic echo -p' columns", p,
                     numbers[0])


def _rtsgt_form(p: Path, nums: list[int], tok: np.ndarray, names: list[str],
                label: str) -> PositionTrajectory:
    vals = to_float(tok[:, :4], nums, p, POSITION_COLUMNS)
    t = vals[:, 0]
    check_increasing(t, nums, p)
    have = [c in names for c in COV_COLUMNS]
    cov = None
    if any(have):
        if not all(have):
            missing = [c for c, h in zip(COV_COLUMNS, have, strict=True) if not h]
            raise InputError(f"covariance columns given in part: missing {', '.join(missing)}",
                             p, nums[0] - 1 if nums[0] > 1 else nums[0])
        idx = [names.index(c) for c in COV_COLUMNS]
        cov = _full_cov(to_float(tok[:, idx], nums, p, COV_COLUMNS))
        _check_cov(cov, p, nums)
    return PositionTrajectory(t, vals[:, 1:4], cov, label)


def _euroc_form(p: Path, nums: list[int], tok: np.ndarray, names: list[str],
                label: str) -> PositionTrajectory:
    if len(names) < 4:
        raise InputError(f"expected the EuRoC columns '#timestamp [ns], p_x [m], p_y [m], "
                         f"p_z [m]', got {len(names)} columns", p, nums[0] - 1)
    ns = to_int(tok[:, :1], nums, p, names[:1])[:, 0]
    t = ns_to_seconds(ns)
    xyz = to_float(tok[:, 1:4], nums, p, names[1:4])
    check_increasing(t, nums, p)
    return PositionTrajectory(t, xyz, None, label)


def _rostopic_form(p: Path, nums: list[int], tok: np.ndarray, names: list[str],
                   label: str) -> PositionTrajectory:
    prefix = next((q for q in _ROSTOPIC_POSITIONS if f"{q}.x" in names), None)
    if prefix is None:
        raise InputError("a 'rostopic echo -p' table without position columns: expected one "
                         f"of {', '.join(q + '.x' for q in _ROSTOPIC_POSITIONS)}", p,
                         nums[0] - 1)
    cols = [names.index(f"{prefix}.{c}") for c in "xyz"]
    xyz = to_float(tok[:, cols], nums, p, [names[j] for j in cols])
    t = None
    if "field.header.stamp" in names:
        j = names.index("field.header.stamp")
        ns = to_int(tok[:, [j]], nums, p, (names[j],))[:, 0]
        if np.any(ns != 0):
            t = ns_to_seconds(ns)
    if t is None:
        if "time" not in names:
            raise InputError("no time column: expected field.header.stamp or %time (ns)", p,
                             nums[0] - 1)
        j = names.index("time")
        t = ns_to_seconds(to_int(tok[:, [j]], nums, p, ("%time",))[:, 0])
    cov = None
    base = {"field.pose.pose.position": "field.pose.covariance"}.get(prefix)
    if base is not None and all(f"{base}{k}" in names for k in (0, 1, 2, 6, 7, 8, 12, 13, 14)):
        idx = [names.index(f"{base}{6 * i + j}") for i in range(3) for j in range(3)]
        cov = to_float(tok[:, idx], nums, p, [names[k] for k in idx]).reshape(-1, 3, 3)
        if not np.any(cov):
            cov = None
        else:
            _check_cov(cov, p, nums)
    check_increasing(t, nums, p)
    return PositionTrajectory(t, xyz, cov, label)


def write_position_csv(path: str | PathLike, traj: PositionTrajectory) -> None:
    """Write the rtsgt form ``t,x,y,z[,cov_xx..cov_zz]`` atomically (the shortest text that
    reads back as the same float64).

    Raises
    ------
    InputError
        Non-finite values or times not strictly increasing.
    """
    cols = [traj.t[:, None], traj.position]
    names = list(POSITION_COLUMNS)
    if traj.cov is not None:
        cols.append(traj.cov[:, _IU[0], _IU[1]])
        names += list(COV_COLUMNS)
    table = np.concatenate(cols, axis=1)
    if not np.all(np.isfinite(table)):
        raise InputError("Expected finite values to write positions, got NaN or inf")
    if np.any(np.diff(traj.t) <= 0):
        raise InputError("Expected strictly increasing times to write positions")
    body = "".join(",".join(map(fmt_float, row)) + "\n" for row in table.tolist())
    atomic_write_text(path, ",".join(names) + "\n" + body)


# --------------------------------------------------------------------------- bags


def list_position_topics(path: str | PathLike) -> dict[str, str]:
    """The topics of a bag whose type is a position type (:data:`POSITION_BAG_TYPES`)."""
    with open_bag(path) as reader:
        return {n: str(i.msgtype) for n, i in reader.topics.items()
                if str(i.msgtype) in POSITION_BAG_TYPES}


def _message_position(msg, msgtype: str) -> tuple[list[float], np.ndarray | None]:
    """The position of a message (and the position block of its covariance, if any)."""
    if msgtype == "geometry_msgs/msg/PointStamped":
        q = msg.point
        return [q.x, q.y, q.z], None
    if msgtype == "geometry_msgs/msg/PoseStamped":
        q = msg.pose.position
        return [q.x, q.y, q.z], None
    if msgtype == "geometry_msgs/msg/TransformStamped":
        q = msg.transform.translation
        return [q.x, q.y, q.z], None
    q = msg.pose.pose.position  # PoseWithCovarianceStamped, Odometry
    return [q.x, q.y, q.z], np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3]


def read_position_bag(path: str | PathLike, topic: str | None) -> PositionTrajectory:
    """Read a position ``topic`` (a type of :data:`POSITION_BAG_TYPES`; None: an error listing
    them) of a ROS 1 or ROS 2 bag. Any problem raises :class:`~rtsgt.errors.InputError` (an
    unknown topic lists the bag's position topics)."""
    where = str(path)
    with open_bag(path) as reader:
        topics = {n: str(i.msgtype) for n, i in reader.topics.items()}
        usable = ", ".join(f"{n} ({t})" for n, t in sorted(topics.items())
                           if t in POSITION_BAG_TYPES) or "none"
        if topic is None:
            raise InputError(f"choose the ground truth's topic (--gt-topic); position topics "
                             f"in the bag: {usable}", where)
        if topic not in topics:
            raise InputError(f"topic {topic!r} is not in the bag; position topics: {usable}",
                             where)
        msgtype = topics[topic]
        if msgtype not in POSITION_BAG_TYPES:
            raise InputError(f"topic {topic!r} has type {msgtype}, expected one of "
                             f"{', '.join(POSITION_BAG_TYPES)}", where)
        conns = [c for c in reader.connections if c.topic == topic]
        stamps, record_t, xyz, covs = [], [], [], []
        for conn, bag_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            pos, cov = _message_position(msg, msgtype)
            st = msg.header.stamp
            stamps.append(int(st.sec) * 1_000_000_000 + int(st.nanosec))
            record_t.append(int(bag_ns))
            xyz.append(pos)
            covs.append(cov)
    if not xyz:
        raise InputError(f"topic {topic!r} holds no message", where)
    ns = np.asarray(stamps, dtype=np.int64)
    if not np.any(ns):
        ns = np.asarray(record_t, dtype=np.int64)
    t = ns_to_seconds(ns)
    p = np.asarray(xyz, dtype=float)
    cov = None if covs[0] is None else np.asarray(covs, dtype=float)
    finite = np.all(np.isfinite(p), axis=1)
    if cov is not None:
        finite &= np.all(np.isfinite(cov), axis=(1, 2))
    if not np.all(finite):
        k = int(np.argmax(~finite))
        raise InputError(f"topic {topic!r}: NaN or infinite value in message {k} "
                         f"(t = {t[k]!r})", where)
    order = np.argsort(ns, kind="stable")
    ns, t, p = ns[order], t[order], p[order]
    cov = None if cov is None else cov[order]
    same = np.flatnonzero(np.diff(ns) == 0)
    if same.size:
        dup_ok = np.all(p[same] == p[same + 1], axis=1)
        if not np.all(dup_ok):
            k = int(same[np.argmax(~dup_ok)])
            raise InputError(f"topic {topic!r}: two different positions share the stamp "
                             f"t = {t[k]!r} s", where)
        keep = np.ones(t.size, dtype=bool)
        keep[same + 1] = False
        t, p = t[keep], p[keep]
        cov = None if cov is None else cov[keep]
    if cov is not None:
        if not np.any(cov):
            cov = None
        else:
            _check_cov(cov, where, labels=[f"the message at t = {v!r} s" for v in t])
    return PositionTrajectory(t, p, cov, topic)


def read_positions(path: str | PathLike, fmt: str | None = None, *,
                   topic: str | None = None) -> PositionTrajectory:
    """A position trajectory from a CSV (:func:`read_position_csv`) or a bag
    (:func:`read_position_bag`, ``topic`` required); ``fmt`` (``"csv"`` or ``"bag"``) from
    the path when None (a directory or a ``.bag`` / ``.db3`` / ``.mcap`` file is a bag)."""
    p = Path(path)
    if fmt is None:
        fmt = "bag" if p.is_dir() or p.suffix in BAG_SUFFIXES else "csv"
    if fmt == "bag":
        return read_position_bag(p, topic)
    if fmt == "csv":
        if not p.is_file():
            raise InputError("file not found", p)
        return read_position_csv(p)
    raise InputError(f"unknown position format {fmt!r}; expected one of "
                     f"{', '.join(POSITION_FORMATS)}")
