"""Reader of the raw bags of the total-station acquisition system of RTS_project.

The bags of Vaidis et al. (norlab-ulaval ``theodolite_node_msgs``), ROS 1 or ROS 2, through
``rosbags`` (the ``bags`` extra): ``TheodoliteCoordsStamped`` on :data:`TOPIC` (or the older
``Float64MultiArray`` on :data:`OLD_TOPIC`), the clock corrections on
:data:`CORRECTION_TOPIC` (read and reported, already in ``header.stamp``), the types
registered from :data:`MESSAGE_DEFINITIONS` where a bag lacks them. The conventions are the
prism files' (``azimuth`` = ``Hz``, ``elevation`` = the zenith angle, the distance without
the additive constant, the time ``sec + nanosec * 1e-9``); a non-zero status is removed and
counted by reason (:data:`INPUT_REASONS`, :class:`InputReport`).
docs/file-formats.md#total-station-bags.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from os import PathLike
from typing import Any

import numpy as np

from rtsgt.errors import InputError, RtsgtWarning
from rtsgt.filtering.modules import FilterReport
from rtsgt.io._bag import open_bag
from rtsgt.types import Observations

__all__ = [
    "CORRECTION_TOPIC", "INPUT_REASONS", "MESSAGE_DEFINITIONS", "OLD_TOPIC", "STATUS_REASONS",
    "TIME_SOURCES", "TOPIC", "InputReport", "TheodoliteBag", "TimeCorrections",
    "correction_topic_of", "read_theodolite_bag",
]

#: Topic of the measurements (``TheodoliteCoordsStamped``).
TOPIC = "/theodolite_master/theodolite_data"
#: Topic of the clock corrections (``TheodoliteTimeCorrection``).
CORRECTION_TOPIC = "/theodolite_master/theodolite_correction_timestamp"
#: Topic of the older layout (``std_msgs/Float64MultiArray``).
OLD_TOPIC = "/theodolite_data"
#: Last names of the measurements' and of the corrections' topics the node publishes.
_DATA_NAME, _CORRECTION_NAME = "theodolite_data", "theodolite_correction_timestamp"

COORDS_TYPE = "theodolite_node_msgs/msg/TheodoliteCoordsStamped"
CORRECTION_TYPE = "theodolite_node_msgs/msg/TheodoliteTimeCorrection"
ARRAY_TYPE = "std_msgs/msg/Float64MultiArray"

#: The message definitions registered for bags that do not carry theirs.
MESSAGE_DEFINITIONS = {
    COORDS_TYPE: (
        "std_msgs/Header header\n"
        "time theodolite_time\n"
        "uint8 theodolite_id\n"
        "uint8 status\n"
        "float64 azimuth\n"
        "float64 elevation\n"
        "float64 distance\n"
    ),
    CORRECTION_TYPE: (
        "std_msgs/Header header\n"
        "uint8 theodolite_id\n"
        "duration estimated_time_offset\n"
    ),
}

#: Reason of the removal of a message, by its non-zero status code.
STATUS_REASONS = {1: "tilt_out_of_range", 2: "wrong_target_distance", 3: "tracking_exception",
                  4: "distance_under_1m"}
#: Every reason the reader removes a message for (``unknown_status``: any other code).
INPUT_REASONS = (*STATUS_REASONS.values(), "unknown_status")
#: Which time a ``TheodoliteCoordsStamped`` gives (module docstring).
TIME_SOURCES = ("header", "theodolite")

_COORDS_FIELDS = ("header", "theodolite_time", "theodolite_id", "status", "azimuth",
                  "elevation", "distance")


@dataclass(frozen=True)
class TimeCorrections:
    """The clock corrections of one station, in the order of the bag.

    Attributes
    ----------
    t : ndarray, shape (K,)
        ``header.stamp`` of each correction message, s.
    offset_s : ndarray, shape (K,)
        ``estimated_time_offset``, s.
    """

    t: np.ndarray
    offset_s: np.ndarray

    def __len__(self) -> int:
        return self.t.shape[0]

    def as_dict(self) -> dict[str, Any]:
        """Count, first, last, median, min and max of the offsets (s; None without any)."""
        o = self.offset_s
        stats = ({k: float(f(o)) for k, f in (("first", lambda a: a[0]), ("last", lambda a: a[-1]),
                                              ("median", np.median), ("min", np.min),
                                              ("max", np.max))}
                 if o.size else dict.fromkeys(("first", "last", "median", "min", "max")))
        return {"count": int(o.size), "offset_s": stats}


@dataclass(frozen=True)
class InputReport(FilterReport):
    """What the reader of the measurements removed, per station, and where they came from.

    A :class:`~rtsgt.filtering.modules.FilterReport` of module ``"input"`` (counts by reason
    of :data:`INPUT_REASONS`, total and per station in the order of ``stations``), with the
    bag's description in ``source`` (file, topic, layout, time, the clock corrections).
    """

    stations: tuple[str, ...] = ()
    source: Mapping[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), "stations": list(self.stations), **self.source}


@dataclass(frozen=True)
class TheodoliteBag:
    """The measurements of a bag, per theodolite id: ``path``, ``topic``, ``layout``
    (``"TheodoliteCoordsStamped"``, ``"Float64MultiArray"``), ``time`` (``"header"``,
    ``"theodolite"``, ``"array"``), ``observations`` (the valid measurements sorted by time, raw
    distances; :meth:`station` names them), ``removed`` counts by reason, ``time_corrections``,
    ``stamp_difference_s`` (median ``theodolite_time - header.stamp``, s) and the
    ``correction_topic`` read (or None)."""

    path: str
    topic: str
    layout: str
    time: str
    observations: dict[int, Observations]
    removed: dict[int, dict[str, int]]
    time_corrections: dict[int, TimeCorrections] = field(default_factory=dict)
    stamp_difference_s: dict[int, float] = field(default_factory=dict)
    correction_topic: str | None = None

    @property
    def ids(self) -> tuple[int, ...]:
        """The theodolite ids with at least one message on the topic, sorted."""
        return tuple(sorted(self.removed))

    def station(self, theodolite_id: int, *, station: str, prism: str,
                additive_constant: float = 0.0) -> Observations:
        """The valid measurements of ``theodolite_id`` as station ``station`` tracking
        ``prism``, with its additive constant.

        Raises
        ------
        InputError
            No message of that theodolite id on the topic (the ids there listed).
        """
        if theodolite_id not in self.removed:
            raise InputError(
                f"topic {self.topic!r} has no message of theodolite_id {theodolite_id} (station "
                f"{station}); theodolite ids there: "
                f"{', '.join(map(str, self.ids)) or 'none'}", self.path)
        obs = self.observations[theodolite_id]
        return replace(obs, station=str(station), prism=str(prism),
                       additive_constant=float(additive_constant))

    def report(self, stations: Mapping[str, int]) -> InputReport:
        """The :class:`InputReport` of the stations ``{station id: theodolite id}``."""
        per = tuple(dict(self.removed.get(tid, dict.fromkeys(INPUT_REASONS, 0)))
                    for tid in stations.values())
        total = {r: sum(c[r] for c in per) for r in INPUT_REASONS}
        kept = sum(len(self.observations[tid]) for tid in stations.values()
                   if tid in self.observations)
        by_station = dict(stations)
        source = {
            "format": "ros-bag", "file": self.path, "topic": self.topic, "layout": self.layout,
            "time": self.time, "correction_topic": self.correction_topic,
            "theodolite_ids": {s: int(t) for s, t in by_station.items()},
            "time_corrections": {s: self.time_corrections[t].as_dict()
                                 for s, t in by_station.items() if t in self.time_corrections},
            "stamp_difference_s": {s: self.stamp_difference_s[t]
                                   for s, t in by_station.items()
                                   if t in self.stamp_difference_s},
        }
        return InputReport("input", kept + sum(total.values()), kept, total, per,
                           stations=tuple(stations), source=source)


def _layout(msgtype: str) -> str | None:
    name = msgtype.rsplit("/", 1)[-1]
    if name == "TheodoliteCoordsStamped":
        return name
    if msgtype == ARRAY_TYPE:
        return "Float64MultiArray"
    return None


def _choose_topic(topics: dict[str, str], topic: str | None, where: str) -> tuple[str, str]:
    """The topic to read and its layout (module docstring)."""
    listing = ", ".join(f"{n} ({t})" for n, t in sorted(topics.items())) or "none"
    if topic is None:
        topic = next((t for t in (TOPIC, OLD_TOPIC) if t in topics), None)
    if topic is None:
        raise InputError(
            f"no total-station measurements: expected topic {TOPIC!r} "
            f"(TheodoliteCoordsStamped) or {OLD_TOPIC!r} (Float64MultiArray); topics in the "
            f"bag: {listing} (name another with [measurements] topic)", where)
    if topic not in topics:
        raise InputError(f"topic {topic!r} is not in the bag; topics in the bag: {listing}",
                         where)
    layout = _layout(topics[topic])
    if layout is None:
        raise InputError(
            f"topic {topic!r} has type {topics[topic]}, expected {COORDS_TYPE} or "
            f"{ARRAY_TYPE} (total-station measurements)", where)
    return topic, layout


def _decode(reader, raw, conn, k: int, where: str):
    try:
        return reader.deserialize(raw, conn.msgtype)
    except Exception as exc:  # an unknown type, a truncated message, another definition
        raise InputError(f"topic {conn.topic!r}, message {k}: cannot decode it as "
                         f"{conn.msgtype}: {exc}", where) from exc


def _coords_rows(reader, conns, where: str) -> np.ndarray:
    """(N, 9) float rows: id, status, azimuth, elevation, distance, header sec, nanosec,
    theodolite_time sec, nanosec (integers exact in float64)."""
    rows = []
    for k, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
        m = _decode(reader, raw, conn, k, where)
        try:
            rows.append((m.theodolite_id, m.status, m.azimuth, m.elevation, m.distance,
                         m.header.stamp.sec, m.header.stamp.nanosec,
                         m.theodolite_time.sec, m.theodolite_time.nanosec))
        except AttributeError as exc:
            raise InputError(
                f"topic {conn.topic!r} has type {conn.msgtype} without the fields of a "
                f"TheodoliteCoordsStamped ({', '.join(_COORDS_FIELDS)}): {exc}", where) from None
    return np.array(rows, dtype=float).reshape(-1, 9)


def _array_rows(reader, conns, where: str) -> np.ndarray:
    """(N, 9) rows as :func:`_coords_rows`, the array's time in both times (status 0 without
    one)."""
    rows = []
    for k, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
        data = np.asarray(_decode(reader, raw, conn, k, where).data, dtype=float)
        status = 0.0
        if data.size in (6, 7):
            sec, nsec = data[4], data[5]
            if not (sec == np.floor(sec) and nsec == np.floor(nsec) and 0 <= nsec < 1e9):
                raise InputError(
                    f"topic {conn.topic!r}, message {k}: expected integer sec and nsec in "
                    f"[0, 1e9) as elements 5 and 6, got {sec!r}, {nsec!r}", where)
            if data.size == 7:
                status = data[6]
                if not (status == np.floor(status) and 0 <= status <= 255):
                    raise InputError(
                        f"topic {conn.topic!r}, message {k}: expected an integer status in "
                        f"[0, 255] as element 7, got {status!r}", where)
        elif data.size == 5:
            sec, nsec = data[4], 0.0  # float seconds: the fraction rides in sec
        else:
            raise InputError(
                f"topic {conn.topic!r}, message {k}: expected 7 values [id, Hz, V, d, sec, "
                f"nsec, status] (or 6: [id, Hz, V, d, sec, nsec]; or 5: [id, Hz, V, d, t]), "
                f"got {data.size}", where)
        rows.append((data[0], status, data[1], data[2], data[3], sec, nsec, sec, nsec))
    return np.array(rows, dtype=float).reshape(-1, 9)


def correction_topic_of(topic: str) -> str:
    """The corrections' topic the node publishes beside the measurements' ``topic``: the
    same namespace, last name ``theodolite_correction_timestamp`` (:data:`CORRECTION_TOPIC`
    when the last name is not ``theodolite_data``)."""
    head, _, last = topic.rpartition("/")
    return f"{head}/{_CORRECTION_NAME}" if last == _DATA_NAME else CORRECTION_TOPIC


def _is_correction(name: str, msgtype: str) -> bool:
    """A topic that holds clock corrections: a ``TheodoliteTimeCorrection``, or the older
    ``Float64MultiArray`` under the node's last name."""
    return (msgtype.endswith("/TheodoliteTimeCorrection")
            or msgtype == ARRAY_TYPE and name.rpartition("/")[2] == _CORRECTION_NAME)


def _correction_topic(topics: dict[str, str], topic: str, given: str | None,
                      where: str) -> str | None:
    """The corrections' topic to read, or None after a warning that says why there is none
    (module docstring)."""
    name = given if given is not None else correction_topic_of(topic)
    if name in topics:
        if not _is_correction(name, topics[name]):
            raise InputError(
                f"topic {name!r} has type {topics[name]}, expected {CORRECTION_TYPE} (or "
                f"{ARRAY_TYPE} [sec, nsec, id, offset]: clock corrections)", where)
        return name
    others = sorted(n for n, ty in topics.items() if _is_correction(n, ty))
    found = (f"the bag has clock corrections on {', '.join(map(repr, others))}" if others
             else f"the bag has no topic of clock corrections ({CORRECTION_TYPE})")
    if given is not None:
        raise InputError(f"[measurements] correction_topic {name!r} is not in the bag; {found}",
                         where)
    hint = " (name it with [measurements] correction_topic)" if others else ""
    warnings.warn(
        f"{where}: no clock corrections on {name!r}: {found}{hint}; the stations' clock "
        "offsets are not reported (the times are used as the node corrected them)",
        RtsgtWarning, stacklevel=3)
    return None


def _corrections(reader, name: str, msgtype: str, where: str) -> dict[int, TimeCorrections]:
    """The corrections of topic ``name`` per theodolite id."""
    conns = [c for c in reader.connections if c.topic == name]
    rows = []
    for k, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
        m = _decode(reader, raw, conn, k, where)
        if msgtype == ARRAY_TYPE:
            data = np.asarray(m.data, dtype=float)
            if data.size != 4:
                raise InputError(f"topic {name!r}, message {k}: expected 4 values [sec, nsec, "
                                 f"id, offset_s], got {data.size}", where)
            rows.append((data[2], data[0], data[1], data[3], 0.0))
            continue
        try:
            off = m.estimated_time_offset
            rows.append((m.theodolite_id, m.header.stamp.sec, m.header.stamp.nanosec,
                         off.sec, off.nanosec))
        except AttributeError as exc:
            raise InputError(f"topic {name!r} has type {conn.msgtype} without the "
                             f"fields of a TheodoliteTimeCorrection: {exc}", where) from None
    a = np.array(rows, dtype=float).reshape(-1, 5)
    t = a[:, 1] + a[:, 2] * 1e-9
    offset = a[:, 3] + a[:, 4] * 1e-9
    return {int(i): TimeCorrections(t[a[:, 0] == i], offset[a[:, 0] == i])
            for i in np.unique(a[:, 0])}


def _check_values(rows: np.ndarray, t: np.ndarray, topic: str, where: str) -> None:
    """Refuse a valid message (status 0) with a value no measurement has (module docstring)."""
    valid = rows[:, 1] == 0
    hz, v, d = rows[:, 2], rows[:, 3], rows[:, 4]
    checks = (
        (~np.isfinite(hz) | ~np.isfinite(v) | ~np.isfinite(d),
         lambda k: f"a non-finite value (azimuth {float(hz[k])!r}, elevation "
                   f"{float(v[k])!r}, distance {float(d[k])!r})"),
        (~(d > 0), lambda k: f"expected a positive slope distance, got {float(d[k])!r} m"),
        (~((v > 0) & (v < np.pi)),
         lambda k: f"expected a zenith angle (elevation) in (0, pi) rad, got {float(v[k])!r} "
                   "rad (in degrees?)"),
        (~(t > 0), lambda k: f"expected a Unix time, got {float(t[k])!r} s"),
    )
    for bad, say in checks:
        bad = bad & valid
        if bad.any():
            k = int(np.argmax(bad))
            raise InputError(f"topic {topic!r}, message {k} (theodolite_id {int(rows[k, 0])}, "
                             f"status 0): {say(k)}", where)


def read_theodolite_bag(path: str | PathLike, *, topic: str | None = None,
                        time: str | None = None,
                        correction_topic: str | None = None) -> TheodoliteBag:
    """Read the total-station measurements of a ROS 1 ``.bag`` or a ROS 2 bag (directory, or its
    ``.db3`` / ``.mcap``) into a :class:`TheodoliteBag`: ``topic`` default :data:`TOPIC`, else
    :data:`OLD_TOPIC`; ``time`` ``"header"`` (default) or ``"theodolite"``; ``correction_topic``
    default :func:`correction_topic_of` the topic (a warning when missing). Any problem is one
    :class:`~rtsgt.errors.InputError` line naming the bag (and the topic and message)."""
    if time is not None and time not in TIME_SOURCES:
        raise InputError(f"Expected time {' or '.join(map(repr, TIME_SOURCES))}, got {time!r}")
    where = str(path)
    with open_bag(path, MESSAGE_DEFINITIONS) as reader:
        topics = {name: str(info.msgtype) for name, info in reader.topics.items()}
        topic, layout = _choose_topic(topics, topic, where)
        conns = [c for c in reader.connections if c.topic == topic]
        if layout == "Float64MultiArray":
            if time is not None:
                raise InputError(
                    f"topic {topic!r} holds the older layout (Float64MultiArray), which has one "
                    f"time (the array's): time = {time!r} applies to TheodoliteCoordsStamped "
                    "only; leave it out", where)
            rows = _array_rows(reader, conns, where)
        else:
            rows = _coords_rows(reader, conns, where)
        corr_topic = _correction_topic(topics, topic, correction_topic, where)
        corrections = ({} if corr_topic is None
                       else _corrections(reader, corr_topic, topics[corr_topic], where))
    if rows.shape[0] == 0:
        raise InputError(f"topic {topic!r} holds no message", where)
    header = rows[:, 5] + rows[:, 6] * 1e-9
    theodolite = rows[:, 7] + rows[:, 8] * 1e-9
    time = "array" if layout == "Float64MultiArray" else (time or "header")
    t = theodolite if time == "theodolite" else header
    _check_values(rows, t, topic, where)
    ids, status = rows[:, 0].astype(int), rows[:, 1].astype(int)
    reason = np.full(status.shape, len(INPUT_REASONS) - 1)
    for code, name in STATUS_REASONS.items():
        reason[status == code] = INPUT_REASONS.index(name)
    observations, removed, difference = {}, {}, {}
    for i in np.unique(ids):
        mine = ids == i
        ok = np.flatnonzero(mine & (status == 0))
        ok = ok[np.argsort(t[ok], kind="stable")]
        gone = reason[mine & (status != 0)]
        removed[int(i)] = {r: int(np.sum(gone == j)) for j, r in enumerate(INPUT_REASONS)}
        observations[int(i)] = Observations(
            t[ok], rows[ok, 2], rows[ok, 3], rows[ok, 4], station=str(i), prism=str(i),
            source=f"{where} [{topic}, theodolite_id {i}]")
        if layout == "TheodoliteCoordsStamped" and ok.size:
            difference[int(i)] = float(np.median(theodolite[ok] - header[ok]))
    return TheodoliteBag(where, topic, layout, time, observations, removed, corrections,
                         difference, corr_topic)
